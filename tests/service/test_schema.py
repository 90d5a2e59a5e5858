"""Schemathesis against the app's own OpenAPI schema: every route, a few hundred generated requests.

The app runs in-process (ASGI) with the tiny stand-in model, so the test exercises routing,
validation, parsing, the batcher and the error handlers rather than the network's speed. Each
response must not be a 5xx, and its status code, content type, headers and body must be the
ones the schema documents for that operation.
"""

import atexit
import shutil
import tempfile
from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis")
pytest.importorskip("onnx")  # to build the stand-in model
from conftest import build_tiny_model  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402
from schemathesis import checks as st_checks  # noqa: E402

from service.app import create_app  # noqa: E402
from service.settings import Settings  # noqa: E402

EXAMPLES_PER_OPERATION = 25  # x 12 operations: about 300 requests
CHECKS = [
    st_checks.not_a_server_error,
    st_checks.status_code_conformance,
    st_checks.content_type_conformance,
    st_checks.response_headers_conformance,
    st_checks.response_schema_conformance,
]


def schema_of_test_app():
    """The app's schema, loaded at import: schemathesis parametrizes tests at collection time
    (its lazy fixture loader breaks on pytest 9)."""
    model_dir = Path(tempfile.mkdtemp(prefix="ifnet-schema-"))
    atexit.register(shutil.rmtree, model_dir, ignore_errors=True)
    app = create_app(
        Settings(
            model_path=build_tiny_model(model_dir / "object.onnx"),
            min_points=8,
            max_network_points=256,
            max_body_bytes=200_000,
            max_cloud_points=5_000,
            # Schemathesis opens a client, so a lifespan, per request: without warm-up the app is ready
            # before the request is handled, where a warm-up still under way made /ready answer 503.
            warmup=False,
        )
    )
    return schemathesis.openapi.from_asgi("/openapi.json", app)


schema = schema_of_test_app()


def test_the_schema_covers_every_route():
    operations = {(op.method.upper(), op.path) for op in (result.ok() for result in schema.get_all_operations())}
    assert operations == {
        ("POST", "/register"),
        ("GET", "/health"),
        ("GET", "/ready"),
        ("GET", "/metrics"),
        ("GET", "/v2"),
        ("GET", "/v2/health/live"),
        ("GET", "/v2/health/ready"),
        ("GET", "/v2/models"),
        ("GET", "/v2/models/{model_name}"),
        ("GET", "/v2/models/{model_name}/ready"),
        ("POST", "/v2/models/{model_name}/infer"),
    }


@schema.parametrize()
# The binary bodies have no generator; the JSON and multipart ones are exercised.
@pytest.mark.filterwarnings("ignore:Skipped test cases with unsupported payload media types")
@settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_every_response_is_documented_and_never_a_server_error(case):
    case.call_and_validate(checks=CHECKS)
