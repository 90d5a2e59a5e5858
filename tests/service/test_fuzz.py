"""Arbitrary request bodies never produce a server error: every bad input is a 4xx."""

import asyncio
import json
import math

import httpx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.app import create_app
from service.settings import Settings

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10**20), max_value=10**20),
    st.sampled_from([0.0, 1e300, -1e300, 1e-300]),
)
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), numbers, st.text(max_size=5)),
    lambda children: st.one_of(
        st.lists(children, max_size=5), st.dictionaries(st.text(max_size=5), children, max_size=4)
    ),
    max_leaves=20,
)
points = st.one_of(
    st.lists(st.lists(numbers, min_size=3, max_size=3), min_size=0, max_size=60),
    st.lists(st.lists(st.floats(-10, 10), min_size=3, max_size=3), min_size=30, max_size=60),
    json_values,
)
options = st.fixed_dictionaries(
    {},
    optional={
        "init": st.one_of(st.lists(st.lists(numbers, min_size=4, max_size=4), min_size=4, max_size=4), json_values),
        "refine": st.one_of(st.booleans(), st.fixed_dictionaries({}, optional={"max_distance": numbers}), json_values),
        "max_points": st.one_of(st.integers(-5, 5000), json_values),
        "sampling": st.one_of(st.sampled_from(["fps", "random"]), json_values),
        "seed": st.one_of(st.integers(-5, 2**40), json_values),
        "fitness_threshold": numbers,
    },
)


def dumps(value) -> str:
    return json.dumps(value, allow_nan=True)


class BlockingClient:
    """Synchronous calls into the app on an event loop of its own (hypothesis drives plain functions)."""

    def __init__(self, app, loop: asyncio.AbstractEventLoop):
        self.loop = loop
        self.http = httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://testserver")

    def post(self, *args, **kwargs) -> httpx.Response:
        return self.loop.run_until_complete(self.http.post(*args, **kwargs))


@pytest.fixture(scope="module")
def client(tiny_model):
    app = create_app(Settings(model_path=tiny_model, min_points=8, max_network_points=256, max_body_bytes=100_000))
    loop = asyncio.new_event_loop()
    lifespan = app.router.lifespan_context(app)
    loop.run_until_complete(lifespan.__aenter__())
    loop.run_until_complete(asyncio.wait_for(app.state.service.ready.wait(), 60))
    blocking = BlockingClient(app, loop)
    try:
        yield blocking
    finally:
        loop.run_until_complete(blocking.http.aclose())
        loop.run_until_complete(lifespan.__aexit__(None, None, None))
        loop.close()


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(source=points, target=points, extra=options)
def test_json_bodies_never_cause_a_server_error(client, source, target, extra):
    response = client.post(
        "/register",
        content=dumps({"source": source, "target": target, **extra}),
        headers={"content-type": "application/json"},
    )
    assert response.status_code < 500, response.text
    if response.status_code == 200:
        assert all(math.isfinite(value) for row in response.json()["transform"] for value in row)
    else:
        assert response.json()["detail"]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    content=st.binary(max_size=300),
    content_type=st.sampled_from(
        ["application/json", "application/x-npy", "application/x-npz", "application/octet-stream", "text/csv"]
    ),
)
def test_raw_bodies_never_cause_a_server_error(client, content, content_type):
    for prefix in (b"", b"\x93NUMPY", b"PK\x03\x04"):
        response = client.post("/register", content=prefix + content, headers={"content-type": content_type})
        assert 400 <= response.status_code < 500, response.text


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    source=st.binary(max_size=300),
    prefix=st.sampled_from([b"", b"ply\nformat ascii 1.0\n", b"VERSION 0.7\n", b"\x93NUMPY"]),
)
def test_uploaded_files_never_cause_a_server_error(client, source, prefix):
    files = {"source": ("s", prefix + source), "target": ("t", prefix + source)}
    response = client.post("/register", files=files)
    assert 400 <= response.status_code < 500, response.text


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(inputs=json_values, parameters=json_values)
def test_v2_bodies_never_cause_a_server_error(client, inputs, parameters):
    response = client.post(
        "/v2/models/object/infer",
        content=dumps({"inputs": inputs, "parameters": parameters}),
        headers={"content-type": "application/json"},
    )
    assert 400 <= response.status_code < 500, response.text
    assert "error" in response.json()
