"""Hostile requests answered by the app itself (in-process): a bomb archive over HTTP, clouds that
crashed feature matching's library, made-up methods, v2 shapes whose product overflows, strings and
booleans where numbers belong, a Host header that must not make a redirect, slow bodies, and the API
key's scope."""

import asyncio
import io

import numpy as np
import pytest
from test_hostile_files import deflate_bomb, npy_bytes, npy_header, npz_of

from service.settings import Settings

pytestmark = pytest.mark.anyio

SOURCE = np.random.default_rng(5).normal(size=(100, 3))
TARGET = SOURCE + [0.5, 0.0, 0.0]
PAIR = {"source": SOURCE.tolist(), "target": TARGET.tolist()}


def v2_body(source, target, **changes) -> dict:
    tensors = [
        {"name": name, "datatype": "FP32", "shape": list(np.shape(cloud)), "data": np.ravel(cloud).tolist()}
        for name, cloud in (("source", source), ("target", target))
    ]
    tensors[0].update(changes)
    return {"inputs": tensors}


async def test_an_npz_bomb_body_is_refused(serve, tiny_model):
    import zipfile

    body = npz_of(npy_header("<f8", (500, 3)) + deflate_bomb(256), npy_bytes(TARGET), method=zipfile.ZIP_DEFLATED)
    async with serve(Settings(model_path=tiny_model)) as (app, client):
        answer = await client.post("/register", content=body, headers={"Content-Type": "application/x-npz"})
    assert answer.status_code == 422
    assert answer.json()["errors"][0]["field"] == "source"


@pytest.mark.parametrize("method", ["auto", "global"])
async def test_clouds_of_isolated_near_duplicate_pairs_get_an_answer(serve, tiny_model, method):
    """Feature matching's library crashed the worker on them (its voxel, from their spacing, leaves
    every voxel alone): the pair is answered, flagged, and the service goes on."""
    rng = np.random.default_rng(6)
    clouds = []
    for _ in range(2):
        base = rng.normal(size=(150, 3)) * 10
        clouds.append(np.concatenate([base, base + 1e-3 * rng.normal(size=(150, 3))]).tolist())
    async with serve(Settings(model_path=tiny_model)) as (app, client):
        answer = await client.post("/register", json={"source": clouds[0], "target": clouds[1], "method": method})
        assert answer.status_code == 200, answer.text
        assert answer.json()["verified"] is False
        assert (await client.post("/register", json=PAIR)).status_code == 200


async def test_made_up_methods_share_one_metrics_label(serve, tiny_model):
    async with serve(Settings(model_path=tiny_model)) as (app, client):
        for index in range(50):
            answer = await client.request(f"M{index}" + "A" * 200, "/register")
            assert answer.status_code == 405
        metrics = (await client.get("/metrics")).text
    assert "M1AAAA" not in metrics
    assert 'ifnet_http_requests_total{method="other",route="/register",status="405"} 50.0' in metrics


@pytest.mark.parametrize(
    ("changes", "problem"),
    [
        ({"shape": [2**32, 2**32, 3], "data": []}, "needs 55340232221128654848"),
        ({"shape": [2**62, 2**62, 3], "data": [1.0, 2.0, 3.0]}, "data has 3 values"),
        ({"data": ["1.0"] * 300}, "must be JSON numbers"),
        ({"data": [True] * 300}, "must be JSON numbers"),
        ({"data": [[1.0, 2.0, "3"]] * 100}, "must be JSON numbers"),
        ({"data": [10**400] * 300}, "beyond the float range"),
    ],
    ids=["shape-wraps", "shape-huge", "strings", "booleans", "nested-string", "huge-integer"],
)
async def test_v2_tensors_must_hold_json_numbers_matching_their_shape(serve, tiny_model, changes, problem):
    async with serve(Settings(model_path=tiny_model)) as (app, client):
        answer = await client.post("/v2/models/object/infer", json=v2_body(SOURCE, TARGET, **changes))
    assert answer.status_code == 422, answer.text
    assert problem in answer.json()["error"]


@pytest.mark.parametrize(
    "init",
    [
        [["1", "0", "0", "0"], ["0", "1", "0", "0"], ["0", "0", "1", "0"], ["0", "0", "0", "1"]],
        [[True, False, False, False], [False, True, False, False], [False, False, True, False], [0, 0, 0, 1]],
    ],
    ids=["strings", "booleans"],
)
async def test_init_must_be_numbers_on_both_apis(serve, tiny_model, init):
    async with serve(Settings(model_path=tiny_model)) as (app, client):
        answer = await client.post("/register", json={**PAIR, "init": init})
        assert answer.status_code == 422, answer.text
        assert "init" in answer.json()["detail"] and "not strings or true/false" in answer.json()["detail"]
        v2 = {**v2_body(SOURCE, TARGET), "parameters": {"init": init}}
        answer = await client.post("/v2/models/object/infer", json=v2)
        assert answer.status_code == 422, answer.text


async def test_a_trailing_slash_gets_no_redirect_built_from_the_host_header(serve, tiny_model):
    async with serve(Settings(model_path=tiny_model)) as (app, client):
        answer = await client.post("/register/", json=PAIR, headers={"Host": "evil.example"})
    assert answer.status_code == 404
    assert "location" not in answer.headers


async def test_a_body_slower_than_the_deadline_gets_408_and_a_slow_service_504(serve, tiny_model, gated_engine):
    from service.engine import OnnxEngine

    async def trickle():
        yield b'{"source": '
        await asyncio.sleep(5)
        yield b"[]}"

    engine = gated_engine(OnnxEngine(tiny_model, 1), gated=False)
    settings = Settings(model_path=tiny_model, request_timeout_s=0.5, warmup=False)
    async with serve(settings, engines=[engine]) as (app, client):
        answer = await client.post("/register", content=trickle(), headers={"Content-Type": "application/json"})
        assert answer.status_code == 408, answer.text
        assert answer.json()["errors"][0]["field"] == "body"
        assert answer.headers["connection"] == "close"
        engine.gate.clear()  # now the model is what is slow
        answer = await client.post("/register", json=PAIR)
        engine.gate.set()
    assert answer.status_code == 504, answer.text


@pytest.mark.parametrize("path", ["/metrics", "/docs", "/openapi.json", "/v2/models/object", "/v2"])
async def test_the_api_key_can_guard_metadata_too(serve, tiny_model, path):
    key = "correct-horse"
    async with serve(Settings(model_path=tiny_model, api_key=key)) as (app, client):
        assert (await client.get(path)).status_code == 200  # the default scope: inference only
    async with serve(Settings(model_path=tiny_model, api_key=key, api_key_scope="all")) as (app, client):
        refused = await client.get(path)
        assert refused.status_code == 401
        assert "API key" in (refused.json().get("error") or refused.json()["detail"])
        assert (await client.get(path, headers={"X-API-Key": key})).status_code == 200
        assert (await client.get(path, headers={"Authorization": f"Bearer {key}"})).status_code == 200
        for probe in ("/health", "/ready", "/v2/health/live", "/v2/health/ready", "/v2/models/object/ready"):
            assert (await client.get(probe)).status_code == 200, probe
        assert (await client.post("/register", json=PAIR, headers={"X-API-Key": key})).status_code == 200


def test_npy_helpers_agree_with_numpy():
    """The hand-made header helper writes what numpy reads."""
    header = npy_header("<f8", (2, 3))
    array = np.load(io.BytesIO(header + np.arange(6.0).tobytes()), allow_pickle=False)
    np.testing.assert_array_equal(array, np.arange(6.0).reshape(2, 3))
