"""The interactive API docs render in a browser with no internet: Swagger UI and ReDoc come from
the installed package, not a CDN."""

from conftest import assert_docs_render, service_process


def test_docs_render_offline(tmp_path, tiny_model):
    with service_process(tmp_path, tiny_model) as (_, url, _):
        assert_docs_render(url, tmp_path)
