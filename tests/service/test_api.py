"""The HTTP API in-process (httpx against the ASGI app), with a tiny ONNX model standing in for IFNet."""

import asyncio
import gzip
import io
import json
import math
import re
import zlib

import numpy as np
import pytest
from plyfile import PlyData, PlyElement
from prometheus_client.parser import text_string_to_metric_families
from pypcd4 import Encoding, PointCloud

from service.settings import Settings

pytestmark = pytest.mark.anyio

RNG = np.random.default_rng(7)
JSON_HEADERS = {"content-type": "application/json"}
SOURCE = RNG.normal(size=(120, 3))
TARGET = SOURCE @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T + [0.5, -0.2, 0.1]


def settings_for(model, **overrides) -> Settings:
    values = {"model_path": model, "max_batch_size": 4, "max_cloud_points": 2000, "max_body_bytes": 200_000}
    return Settings(**{**values, **overrides})


def body(source=SOURCE, target=TARGET, **options) -> dict:
    def listed(points):
        return points.tolist() if isinstance(points, np.ndarray) else points

    return {"source": listed(source), "target": listed(target), **options}


def ply_file(points: np.ndarray) -> bytes:
    vertices = np.zeros(len(points), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    for index, axis in enumerate("xyz"):
        vertices[axis] = points[:, index]
    stream = io.BytesIO()
    PlyData([PlyElement.describe(vertices, "vertex")]).write(stream)
    return stream.getvalue()


def pcd_file(points: np.ndarray) -> bytes:
    stream = io.BytesIO()
    PointCloud.from_points([points[:, 0], points[:, 1], points[:, 2]], ("x", "y", "z"), (np.float64,) * 3).save(
        stream, encoding=Encoding.ASCII
    )
    return stream.getvalue()


def npy_file(array: np.ndarray) -> bytes:
    stream = io.BytesIO()
    np.save(stream, array)
    return stream.getvalue()


async def test_register_answers_with_a_consistent_transform(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        response = await client.post("/register", json=body(seed=1))
    assert response.status_code == 200, response.text
    answer = response.json()
    rotation, translation, transform = map(np.asarray, (answer["rotation"], answer["translation"], answer["transform"]))
    assert rotation.shape == (3, 3) and translation.shape == (3,) and transform.shape == (4, 4)
    np.testing.assert_allclose(transform[:3, :3], rotation)
    np.testing.assert_allclose(transform[:3, 3], translation)
    np.testing.assert_allclose(transform[3], [0, 0, 0, 1])
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert 0.0 <= answer["fitness"] <= 1.0 and answer["inlier_rmse"] >= 0.0 and answer["fitness_threshold"] > 0
    assert answer["points"]["source"] == {
        "received": 120,
        "duplicates_removed": 0,
        "network_points": 64,
        "upsampled": False,
    }
    assert answer["model"]["name"] == "object" and answer["model"]["version"] == "0" * 12
    assert (
        answer["model"]["network_points"] == answer["model"]["native_num_points"] == 64 and answer["refinement"] is None
    )
    timings = answer["timings_ms"]
    assert timings["batch_size"] == 1 and timings["total_ms"] >= timings["inference_ms"] >= 0
    assert timings["total_ms"] >= timings["read_ms"] > 0


async def test_user_thresholds_reach_the_pipeline_and_are_echoed(serve, tiny_model):
    options = {"fitness_threshold": 0.05, "refine": {"max_distance": 0.2, "max_iterations": 3}}
    async with serve(settings_for(tiny_model)) as (app, client):
        default = (await client.post("/register", json=body(refine=True))).json()
        chosen = (await client.post("/register", json=body(**options))).json()
    assert chosen["fitness_threshold"] == 0.05 and default["fitness_threshold"] != 0.05
    assert chosen["refinement"]["max_distance"] == 0.2 and default["refinement"]["max_distance"] != 0.2
    assert 1 <= chosen["refinement"]["iterations"] <= 3


async def test_a_users_fitness_threshold_changes_the_reported_fit_only(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        default = (await client.post("/register", json=body(method="auto"))).json()
        own = (await client.post("/register", json=body(method="auto", fitness_threshold=100.0))).json()
    assert own["fitness"] == 1.0 and own["fitness_threshold"] == 100.0
    for name in ("verified", "reason", "stage"):
        assert own[name] == default[name], name
    # the same pose: refinement on two threads sums in any order, so only the last digits may differ
    np.testing.assert_allclose(own["transform"], default["transform"], atol=1e-9)


async def test_duplicates_are_removed_and_counted(serve, tiny_model):
    source = np.concatenate([SOURCE, SOURCE[:30]])
    async with serve(settings_for(tiny_model)) as (app, client):
        answer = (await client.post("/register", json=body(source=source))).json()
    assert answer["points"]["source"]["received"] == 150
    assert answer["points"]["source"]["duplicates_removed"] == 30


LINE = np.outer(np.arange(50.0), [1.0, 2.0, 3.0])
VALID_INIT = [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


@pytest.mark.parametrize(
    ("payload", "field", "message"),
    [
        (body(source=[[0, 0, 0, 0]] * 40), "source", r"N x 3"),
        (body(target=[[0, 1]] + TARGET.tolist()), "target", r"point 0 has 2 coordinates"),
        (body(source=SOURCE[:5]), "source", "has 5 points; at least 32"),
        (body(source=np.ones((40, 3))), "source", "identical"),
        (body(target=LINE), "target", "one line"),
        (body(source=RNG.normal(size=(2001, 3))), "source", "more than the limit of 2000"),
        (body(init=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "init", "not a rigid transform"),
        (body(init=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "init", r"4x4 matrix, got shape \[3, 3\]"),
        (body(network_points=4096), "network_points", "more than this service's limit"),
        (body(network_points=2), "network_points", "greater than or equal to 8"),
        (body(max_points=10), "network_points", "is 10; model 'object' needs at least 16 points per cloud"),
        (body(sampling="voxel"), "sampling", "'fps' or 'random'"),
        (body(seed=-1), "seed", "greater than or equal to 0"),
        (body(refine={"max_distance": -1}), "refine", "greater than 0"),
        (body(refinement=True), "refinement", "Extra inputs are not permitted"),
        ({"source": SOURCE.tolist()}, "target", "Field required"),
        (body(init=[[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "init", "translation beyond"),
        (body(source=[[1.5, True, 0.5]] + SOURCE.tolist()), "source", "point 0 has a non-numeric coordinate True"),
        (body(source=[[2**64, 0, 0]] + SOURCE.tolist()), "source", r"point 0 has a coordinate beyond ±1e\+12"),
        (body(seed=True), "seed", "valid integer"),
        (body(fitness_threshold=float("inf")), "fitness_threshold", "finite number"),
        (body(refine={"max_distance": float("inf")}), "refine", "finite number"),
    ],
    ids=[
        "not-Nx3",
        "ragged",
        "too-few",
        "identical",
        "collinear",
        "too-many",
        "init-not-rigid",
        "init-not-4x4",
        "max-points-limit",
        "max-points-small",
        "max-points-below-the-models-minimum",
        "sampling",
        "seed",
        "refine-distance",
        "unknown-field",
        "missing-target",
        "init-translation-too-large",
        "boolean-coordinate",
        "integer-too-large",
        "boolean-seed",
        "infinite-fitness-threshold",
        "infinite-refine-distance",
    ],
)
async def test_invalid_json_requests_get_422_naming_the_field(serve, tiny_model, payload, field, message):
    async with serve(settings_for(tiny_model)) as (app, client):
        # json.dumps writes Infinity/NaN as JavaScript does, which httpx's json= refuses to send.
        response = await client.post("/register", content=json.dumps(payload), headers=JSON_HEADERS)
    assert response.status_code == 422, response.text
    answer = response.json()
    assert answer["detail"].startswith(field) and any(error["field"].startswith(field) for error in answer["errors"])
    assert re.search(message, answer["detail"]), answer["detail"]


@pytest.mark.parametrize(
    ("text", "field"),
    [
        (
            '{"source": [[NaN, 0, 0]' + ", [0, 0, 1]" * 40 + '], "target": ' + json.dumps(TARGET.tolist()) + "}",
            "source",
        ),
        (
            '{"source": ' + json.dumps(SOURCE.tolist()) + ', "target": [[0, 0, Infinity]' + ", [0, 1, 0]" * 40 + "]}",
            "target",
        ),
        ('{"source": [[0, 0, -Infinity]' + ", [1, 0, 0]" * 40 + '], "target": [[1, 2, 3]]}', "source"),
    ],
    ids=["nan", "infinity", "minus-infinity"],
)
async def test_non_finite_values_get_422(serve, tiny_model, text, field):
    async with serve(settings_for(tiny_model)) as (app, client):
        response = await client.post("/register", content=text, headers={"content-type": "application/json"})
    assert response.status_code == 422
    assert response.json()["detail"].startswith(f"{field}: 1 point(s) have NaN or infinite coordinates")


async def test_malformed_json_gets_422(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        response = await client.post(
            "/register", content=b'{"source": [[1, 2', headers={"content-type": "application/json"}
        )
    assert response.status_code == 422 and "JSON" in response.json()["detail"]


async def test_bodies_over_the_limit_get_413(serve, tiny_model):
    big = body(source=RNG.normal(size=(1500, 3)), target=RNG.normal(size=(1500, 3)))
    encoded = json.dumps(big).encode()
    assert len(encoded) > 50_000

    async def chunks():
        for start in range(0, len(encoded), 8192):
            yield encoded[start : start + 8192]

    async with serve(settings_for(tiny_model, max_body_bytes=50_000)) as (app, client):
        declared = await client.post("/register", content=encoded, headers={"content-type": "application/json"})
        streamed = await client.post("/register", content=chunks(), headers={"content-type": "application/json"})
        upload = await client.post("/register", files={"source": ("a.npy", b"\x93NUMPY" + b"0" * 60_000)})
        v2_declared = await client.post("/v2/models/object/infer", content=encoded)
        v2_streamed = await client.post("/v2/models/object/infer", content=chunks())
        metrics = (await client.get("/metrics")).text
    assert 'ifnet_http_requests_total{method="POST",route="/register",status="413"} 3.0' in metrics
    for response in (declared, streamed, upload):
        assert response.status_code == 413, response.text
        assert "larger than the limit of 50000 bytes" in response.json()["detail"]
    assert "content-length" not in {key.lower() for key in streamed.request.headers}
    for response in (v2_declared, v2_streamed):  # in the v2 error shape
        assert response.status_code == 413 and set(response.json()) == {"error"}, response.text
        assert "larger than the limit of 50000 bytes" in response.json()["error"]


COMPRESS = {"gzip": gzip.compress, "x-gzip": gzip.compress, "deflate": zlib.compress, "identity": bytes}


@pytest.mark.parametrize("encoding", sorted(COMPRESS))
async def test_compressed_bodies_are_inflated(serve, tiny_model, encoding):
    compress = COMPRESS[encoding]
    payload = json.dumps(body()).encode()
    async with serve(settings_for(tiny_model)) as (app, client):
        expected = (await client.post("/register", content=payload, headers=JSON_HEADERS)).json()
        as_json = await client.post(
            "/register", content=compress(payload), headers={**JSON_HEADERS, "content-encoding": encoding.upper()}
        )
        as_npy = await client.post(
            "/register",
            content=compress(npy_file(np.stack([SOURCE, TARGET]))),
            headers={"content-type": "application/x-npy", "content-encoding": encoding},
        )
        upload = client.build_request(
            "POST", "/register", files={"source": ("s.ply", ply_file(SOURCE)), "target": ("t.ply", ply_file(TARGET))}
        )
        as_upload = await client.post(
            "/register",
            content=compress(upload.read()),
            headers={"content-type": upload.headers["content-type"], "content-encoding": encoding},
        )
    for response in (as_json, as_npy, as_upload):
        assert response.status_code == 200, response.text
        np.testing.assert_allclose(response.json()["transform"], expected["transform"], atol=1e-9)


async def test_compressed_body_errors_name_the_problem(serve, tiny_model):
    payload = json.dumps(body()).encode()
    packed = gzip.compress(payload)
    bomb = gzip.compress(b" " * 5_000_000)  # JSON whitespace, 25x the body limit, in a body of a few KB
    assert len(bomb) < 20_000
    cases = [
        ("br", payload, 415, "content-encoding: 'br' is not supported; send the body plain or as deflate, gzip"),
        ("gzip, gzip", packed, 415, "content-encoding: 'gzip, gzip' is not supported"),
        ("gzip", payload, 400, "body: not valid gzip data"),
        ("deflate", packed, 400, "body: not valid deflate data"),
        ("gzip", packed[:-12], 400, "body: the gzip stream ends before its end"),
        ("gzip", packed + b"trailing", 400, "body: the gzip stream has data after its end"),
        ("gzip", bomb, 413, "body: the request body inflates to more than the limit of 200000 bytes"),
    ]
    async with serve(settings_for(tiny_model)) as (app, client):
        answers = [
            await client.post("/register", content=data, headers={**JSON_HEADERS, "content-encoding": encoding})
            for encoding, data, _, _ in cases
        ]
        v2 = await client.post("/v2/models/object/infer", content=bomb, headers={"content-encoding": "gzip"})
        healthy = await client.post("/register", json=body())
    for (_, _, status, message), answer in zip(cases, answers, strict=True):
        assert answer.status_code == status and answer.json()["detail"].startswith(message), answer.text
        assert answer.json()["errors"][0]["field"] in ("body", "content-encoding")
    assert v2.status_code == 413 and "inflates to more than the limit" in v2.json()["error"]
    assert healthy.status_code == 200
    async with serve(settings_for(tiny_model, api_key="s3cret")) as (app, client):
        unknown_key = await client.post(
            "/register", content=payload, headers={**JSON_HEADERS, "content-encoding": "br"}
        )
    assert unknown_key.status_code == 401  # the key is checked before the body is read


def test_a_compressed_body_is_never_inflated_beyond_the_limit():
    """A 100 MB bomb against a 1 MB limit: refused after at most the limit's worth of output."""
    import tracemalloc

    from fastapi import HTTPException

    from service.middleware import ContentEncodingMiddleware

    packer = zlib.compressobj(wbits=16 + zlib.MAX_WBITS)
    bomb = b"".join(packer.compress(bytes(1 << 20)) for _ in range(100)) + packer.flush()
    chunks = [bomb[start : start + 4096] for start in range(0, len(bomb), 4096)]
    seen = {}

    async def app(scope, receive, send):
        seen["headers"] = dict(scope["headers"])
        while (await receive()).get("more_body"):
            pass

    async def receive():
        chunk = chunks.pop(0)
        return {"type": "http.request", "body": chunk, "more_body": bool(chunks)}

    middleware = ContentEncodingMiddleware(app, max_bytes=1 << 20)
    scope = {"type": "http", "headers": [(b"content-encoding", b"gzip"), (b"content-length", b"%d" % len(bomb))]}
    tracemalloc.start()
    with pytest.raises(HTTPException) as refused:
        asyncio.run(middleware(scope, receive, None))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert refused.value.status_code == 413
    assert peak < 4 << 20, f"{peak / 1e6:.1f} MB held while inflating"
    assert seen["headers"] == {}  # the app sees neither the encoding nor the compressed length
    assert chunks  # reading stopped at the limit, long before the end of the body


async def test_large_json_bodies_are_parsed_one_at_a_time(serve, tiny_model, monkeypatch):
    """Parallel parses of big bodies only contend for the GIL and hold their objects meanwhile;
    small bodies are never held up behind them."""
    import threading
    import time

    from service import schemas
    from service.uploads import LARGE_JSON_BYTES

    running, most = {"large": 0, "all": 0}, {"large": 0, "all": 0}
    guard, large_started = threading.Lock(), threading.Event()
    original = schemas.RegisterRequest.model_validate_json

    def counted(data, *args, **kwargs):
        kinds = ("all", "large") if len(data) > LARGE_JSON_BYTES else ("all",)
        with guard:
            for kind in kinds:
                running[kind] += 1
                most[kind] = max(most[kind], running[kind])
        if "large" in kinds:
            large_started.set()
        try:
            time.sleep(0.5 if "large" in kinds else 0.05)  # long enough for the others to arrive
            return original(data, *args, **kwargs)
        finally:
            with guard:
                for kind in kinds:
                    running[kind] -= 1

    monkeypatch.setattr(schemas.RegisterRequest, "model_validate_json", counted)
    small = json.dumps(body()).encode()
    large = small + b" " * LARGE_JSON_BYTES  # JSON allows trailing whitespace
    async with serve(settings_for(tiny_model, max_body_bytes=4 * LARGE_JSON_BYTES)) as (app, client):

        async def post(data: bytes, once_a_large_one_parses: bool = False):
            if once_a_large_one_parses:
                assert await asyncio.to_thread(large_started.wait, 10)
            return await client.post("/register", content=data, headers=JSON_HEADERS)

        # The small body arrives while the first large one is being parsed and two more wait.
        answers = await asyncio.gather(post(large), post(large), post(large), post(small, once_a_large_one_parses=True))
    assert [answer.status_code for answer in answers] == [200, 200, 200, 200]
    assert most == {"large": 1, "all": 2}  # one large parse at a time, with the small one beside it


@pytest.mark.parametrize("content_type", ["text/plain", "application/xml", None])
async def test_wrong_content_type_gets_415(serve, tiny_model, content_type):
    headers = {"content-type": content_type} if content_type else {}
    async with serve(settings_for(tiny_model)) as (app, client):
        response = await client.post("/register", content=json.dumps(body()).encode(), headers=headers)
    assert response.status_code == 415
    answer = response.json()
    assert answer["detail"].startswith("content-type: ") and "application/json" in answer["detail"]
    assert answer["errors"] == [{"field": "content-type", "problem": answer["detail"][len("content-type: ") :]}]


async def test_multipart_uploads_match_the_json_answer(serve, tiny_model):
    options = {"seed": 3, "sampling": "random"}
    async with serve(settings_for(tiny_model)) as (app, client):
        expected = (await client.post("/register", json=body(**options))).json()
        for source_file, target_file in [
            (("s.ply", ply_file(SOURCE)), ("t.pcd", pcd_file(TARGET))),
            (("s.npy", npy_file(SOURCE)), ("t.ply", ply_file(TARGET))),
        ]:
            response = await client.post(
                "/register",
                files={"source": source_file, "target": target_file},
                data={"options": json.dumps(options)},
            )
            assert response.status_code == 200, response.text
            np.testing.assert_allclose(response.json()["transform"], expected["transform"], atol=1e-9)


async def test_multipart_errors(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        missing = await client.post("/register", files={"source": ("s.ply", ply_file(SOURCE))})
        unknown_format = await client.post(
            "/register", files={"source": ("s.txt", b"1 2 3\n"), "target": ("t.ply", ply_file(TARGET))}
        )
        bad_options = await client.post(
            "/register",
            files={"source": ("s.ply", ply_file(SOURCE)), "target": ("t.ply", ply_file(TARGET))},
            data={"options": '{"seed": "many"}'},
        )
        nan_file = await client.post(
            "/register",
            files={"source": ("s.npy", npy_file(np.full((40, 3), np.nan))), "target": ("t.ply", ply_file(TARGET))},
        )
    assert missing.status_code == 422 and missing.json()["detail"].startswith("target: missing file part")
    assert unknown_format.status_code == 415 and "source: unrecognised file format" in unknown_format.json()["detail"]
    assert unknown_format.json()["errors"][0]["field"] == "source"
    assert bad_options.status_code == 422 and bad_options.json()["detail"].startswith("seed:")
    assert nan_file.status_code == 422 and "NaN" in nan_file.json()["detail"]


async def test_no_room_to_spool_an_upload_is_503_not_500(serve, tiny_model, monkeypatch):
    """Multipart files are spooled to /tmp; when it is full the client is told to retry."""
    import errno
    import tempfile

    import starlette.formparsers

    class FullDisk(tempfile.SpooledTemporaryFile):
        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(starlette.formparsers, "SpooledTemporaryFile", FullDisk)
    async with serve(settings_for(tiny_model)) as (app, client):
        response = await client.post(
            "/register", files={"source": ("s.ply", ply_file(SOURCE)), "target": ("t.ply", ply_file(TARGET))}
        )
    assert response.status_code == 503 and response.headers["retry-after"] == "1"
    assert "no room on the server to buffer this upload" in response.json()["detail"]


async def test_options_may_be_a_file_part(serve, tiny_model):
    clouds = {"source": ("s.ply", ply_file(SOURCE)), "target": ("t.ply", ply_file(TARGET))}
    async with serve(settings_for(tiny_model)) as (app, client):
        as_file = await client.post(
            "/register", files={**clouds, "options": ("options.json", b'{"refine": true}', "application/json")}
        )
    assert as_file.status_code == 200, as_file.text
    assert as_file.json()["refinement"] is not None


async def test_query_parameters_other_than_options_are_refused(serve, tiny_model):
    """A misplaced option (`?refine=true` with a JSON body) must not be silently dropped."""
    async with serve(settings_for(tiny_model)) as (app, client):
        misplaced = await client.post("/register", json=body(), params={"refine": "true"})
        bad_options = await client.post(
            "/register", content=npy_file(np.stack([SOURCE, TARGET])), headers={"content-type": "application/x-npy"},
            params={"options": "{refine: true}"},
        )  # fmt: skip
    assert misplaced.status_code == 422
    assert misplaced.json()["errors"] == [{"field": "refine", "problem": misplaced.json()["detail"][len("refine: ") :]}]
    assert "put options in the JSON body" in misplaced.json()["detail"]
    assert bad_options.status_code == 422 and bad_options.json()["detail"].startswith("options: is not valid JSON")


async def test_raw_npy_and_npz_bodies(serve, tiny_model):
    pair = np.stack([SOURCE, TARGET])
    archive = io.BytesIO()
    np.savez_compressed(archive, source=SOURCE, target=TARGET)
    async with serve(settings_for(tiny_model)) as (app, client):
        expected = (await client.post("/register", json=body(refine=True))).json()
        as_npy = await client.post(
            "/register",
            content=npy_file(pair),
            headers={"content-type": "application/x-npy"},
            params={"options": '{"refine": true}'},
        )
        as_npz = await client.post(
            "/register",
            content=archive.getvalue(),
            headers={"content-type": "application/x-npz"},
            params={"options": '{"refine": true}'},
        )
        raw_ply = await client.post(
            "/register", content=ply_file(SOURCE), headers={"content-type": "application/octet-stream"}
        )
        options_twice = await client.post("/register", json=body(), params={"options": "{}"})
    for response in (as_npy, as_npz):
        assert response.status_code == 200, response.text
        np.testing.assert_allclose(response.json()["transform"], expected["transform"], atol=1e-9)
        assert response.json()["refinement"]["iterations"] >= 1
    assert raw_ply.status_code == 415 and "multipart" in raw_ply.json()["detail"]
    assert options_twice.status_code == 422 and options_twice.json()["detail"].startswith("options:")


def answer_failing_its_schema():
    from service.schemas import LatencySummary

    LatencySummary.model_validate({})  # the service's own answer missing its fields


@pytest.mark.parametrize(
    ("bug", "logged"),
    [
        (RuntimeError("a bug"), "RuntimeError('a bug')"),
        # A 500, not a 422: the user sent nothing wrong.
        (answer_failing_its_schema, "4 validation errors for LatencySummary"),
    ],
)
async def test_an_unforeseen_error_is_still_a_json_answer(tiny_model, monkeypatch, caplog, bug, logged):
    """A bug past the input checks answers 500 in the route's error shape; the traceback goes to the log."""
    import httpx

    from service import routes
    from service.app import create_app

    def broken(*args, **kwargs):
        if callable(bug):
            bug()
        raise bug

    monkeypatch.setattr(routes, "register_pairs", broken)
    app = create_app(settings_for(tiny_model))
    async with app.router.lifespan_context(app):
        await asyncio.wait_for(app.state.service.ready.wait(), timeout=60)
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)  # as a real server answers
        async with httpx.AsyncClient(transport=transport, base_url="http://testserver") as client:
            response = await client.post("/register", json=body())
    assert response.status_code == 500
    identifier = response.headers["x-request-id"]
    assert response.json() == {
        "detail": f"internal error; the server log has the details under request id {identifier}",
        "errors": [],
    }
    assert f"request {identifier} (POST /register) failed: {logged}" in caplog.text


async def test_every_answer_carries_a_request_id(serve, tiny_model):
    """The client's id when it is a plain token, else a new one: in the header of every answer."""
    async with serve(settings_for(tiny_model)) as (app, client):
        answers = [
            await client.post("/register", json=body()),  # 200
            await client.post("/register", json={"source": []}),  # 422
            await client.post("/register", content=b"x" * 300_000, headers=JSON_HEADERS),  # 413 before routing
            await client.get("/nowhere"),  # 404
            await client.get("/health"),
            await client.post("/v2/models/object/infer", json={"inputs": []}),
        ]
        kept = await client.get("/health", headers={"X-Request-ID": "trace-01.a:b_c"})
        replaced = [
            await client.get("/health", headers={"X-Request-ID": given})
            for given in ("has space", "x" * 129, "semi;colon", "")
        ]
    assert [answer.status_code for answer in answers] == [200, 422, 413, 404, 200, 422]
    generated = [answer.headers["x-request-id"] for answer in answers + replaced]
    assert all(re.fullmatch(r"[0-9a-f]{32}", value) for value in generated), generated
    assert len(set(generated)) == len(generated)
    assert kept.headers["x-request-id"] == "trace-01.a:b_c"


async def test_api_key(serve, tiny_model):
    async with serve(settings_for(tiny_model, api_key="s3cret")) as (app, client):
        without = await client.post("/register", json=body())
        wrong = await client.post("/register", json=body(), headers={"X-API-Key": "guess"})
        near_misses = [  # a prefix, an empty key, an empty bearer: all wrong
            await client.post("/register", json=body(), headers=headers)
            for headers in ({"X-API-Key": "s3cre"}, {"X-API-Key": ""}, {"Authorization": "Bearer "})
        ]
        with_header = await client.post("/register", json=body(), headers={"X-API-Key": "s3cret"})
        with_bearer = await client.post("/register", json=body(), headers={"Authorization": "Bearer s3cret"})
        v2_without = await client.post("/v2/models/object/infer", json={"inputs": []})
        health = await client.get("/health")
    assert without.status_code == wrong.status_code == v2_without.status_code == 401
    assert [response.status_code for response in near_misses] == [401, 401, 401]
    assert "X-API-Key" in without.json()["detail"] and without.headers["www-authenticate"] == "Bearer"
    assert with_header.status_code == with_bearer.status_code == health.status_code == 200


async def test_health_reports_latency_queue_and_uptime(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        before = (await client.get("/health")).json()
        for _ in range(3):
            assert (await client.post("/register", json=body())).status_code == 200
        await client.post("/register", json=body(source=SOURCE[:3]))  # a 422 is not a latency sample
        after = (await client.get("/health")).json()
    assert before["status"] == "ok" and before["ready"] is True and before["latency"]["count"] == 0
    assert before["latency"]["p50_ms"] is None
    assert after["latency"]["count"] == 3 and after["queue_depth"] == 0 and after["in_flight"] == 0
    assert 0 < after["latency"]["p50_ms"] <= after["latency"]["p95_ms"] <= after["latency"]["p99_ms"]
    assert after["uptime_s"] > before["uptime_s"] > 0


async def test_ready_flips_after_warm_up(serve, tiny_model, gated_engine):
    from service.engine import OnnxEngine

    engine = gated_engine(OnnxEngine(tiny_model))
    async with serve(settings_for(tiny_model, max_batch_size=3), engines=[engine], wait_ready=False) as (app, client):
        assert (await asyncio.to_thread(engine.entered.wait, 30)) is True  # warm-up is under way, held at the gate
        not_ready = await client.get("/ready")
        v2_not_ready = await client.get("/v2/health/ready")
        live = await client.get("/health")
        early = asyncio.ensure_future(client.post("/register", json=body()))  # queued until warm-up ends
        engine.gate.set()
        await asyncio.wait_for(app.state.service.ready.wait(), 30)
        ready = await client.get("/ready")
        v2_ready = await client.get("/v2/health/ready")
        early_response = await early
    assert not_ready.status_code == 503 and not_ready.json() == {"ready": False, "detail": "warming up the models"}
    assert v2_not_ready.status_code == 503 and v2_not_ready.json() == {"ready": False}
    assert live.status_code == 200 and live.json()["ready"] is False and live.json()["status"] == "ok"
    assert ready.status_code == 200 and ready.json()["ready"] is True and v2_ready.status_code == 200
    assert early_response.status_code == 200
    assert engine.calls[:3] == [1, 2, 3]  # warm-up: one call at each batch size, before any request


def test_an_app_started_again_warms_up_again_rather_than_stopping(tiny_model):
    """An app whose lifespan ends and starts again (a test client per request does that) reports
    warming up until it is ready, not stopping."""
    from fastapi.testclient import TestClient

    from service.app import create_app

    app = create_app(settings_for(tiny_model))
    for _ in range(2):
        with TestClient(app) as client:
            assert app.state.service.accepting
            assert client.get("/health").status_code == 200
        assert not app.state.service.accepting  # the lifespan has ended


async def test_a_failed_warm_up_fails_liveness_so_the_process_is_restarted(serve, tiny_model):
    from service.engine import OnnxEngine

    class FailingWarmUp:
        def __init__(self, engine):
            self.info = engine.info

        def run(self, source, target, beside=False):
            raise RuntimeError("out of memory")

    engine = FailingWarmUp(OnnxEngine(tiny_model))
    async with serve(settings_for(tiny_model), engines=[engine], wait_ready=False) as (app, client):
        for _ in range(200):  # the warm-up task fails at once; a hang guard, not a timing assertion
            if app.state.service.warmup_error:
                break
            await asyncio.sleep(0.01)
        live, ready = await client.get("/health"), await client.get("/ready")
    assert live.status_code == 503 and live.json()["status"] == "failed"
    assert "warm-up of model object failed: out of memory" in live.json()["detail"]
    assert ready.status_code == 503 and ready.json()["detail"] == live.json()["detail"]


async def test_metrics_parse_with_the_prometheus_parser(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        await client.post("/register", json=body())
        await client.post("/register", json=body(source=SOURCE[:3]))
        response = await client.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    families = {family.name: family for family in text_string_to_metric_families(response.text)}
    requests = {
        (sample.labels["route"], sample.labels["status"]): sample.value
        for sample in families["ifnet_http_requests"].samples
        if sample.name.endswith("_total")
    }
    assert requests[("/register", "200")] == 1 and requests[("/register", "422")] == 1
    for name in ("ifnet_http_request_duration_seconds", "ifnet_queue_wait_seconds", "ifnet_inference_seconds"):
        assert families[name].type == "histogram"
    batch_count = next(s.value for s in families["ifnet_batch_size"].samples if s.name == "ifnet_batch_size_count")
    assert batch_count == 1  # warm-up calls are not counted, the one valid request is
    assert families["ifnet_ready"].samples[0].value == 1
    assert families["ifnet_queue_depth"].samples[0].value == 0


async def test_every_route_is_documented_with_examples(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        schema = (await client.get("/openapi.json")).json()
    components = schema["components"]["schemas"]

    def has_example(content: dict) -> bool:
        for media in content.values():
            if "example" in media or "examples" in media:
                return True
            reference = media.get("schema", {}).get("$ref", "")
            if reference and "examples" in components[reference.rsplit("/", 1)[1]]:
                return True
        return False

    operations = [(path, method, op) for path, item in schema["paths"].items() for method, op in item.items()]
    assert {path for path, _, _ in operations} >= {
        "/register",
        "/health",
        "/ready",
        "/metrics",
        "/v2/models/{model_name}/infer",
    }
    for path, method, operation in operations:
        assert has_example(operation["responses"]["200"].get("content", {})), f"{method} {path}: no response example"
        if "requestBody" in operation:
            assert has_example(operation["requestBody"]["content"]), f"{method} {path}: no request example"
    register = schema["paths"]["/register"]["post"]["requestBody"]["content"]
    assert set(register) == {"application/json", "multipart/form-data", "application/x-npy", "application/x-npz"}
    assert "source" in components["RegisterRequest"]["properties"]


async def test_unknown_routes_are_404_json(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        response = await client.get("/nothing-here")
    assert response.status_code == 404 and response.json()["detail"] == "Not Found"


# ---------------------------------------------------------------- Open Inference Protocol v2


def v2_tensor(name: str, clouds: np.ndarray) -> dict:
    return {"name": name, "shape": list(clouds.shape), "datatype": "FP32", "data": clouds.ravel().tolist()}


async def test_v2_returns_only_the_outputs_asked_for(serve, tiny_model):
    request = {
        "inputs": [v2_tensor("source", SOURCE[None]), v2_tensor("target", TARGET[None])],
        "outputs": [{"name": "translation"}],
    }
    async with serve(settings_for(tiny_model)) as (app, client):
        answer = (await client.post("/v2/models/object/infer", json=request)).json()
    assert [(output["name"], output["shape"]) for output in answer["outputs"]] == [("translation", [1, 3])]


async def test_network_points_may_reach_the_services_limit_and_not_beyond(serve, tiny_model):
    async with serve(settings_for(tiny_model, max_network_points=256)) as (app, client):
        at_limit = await client.post("/register", json=body(network_points=256))
        beyond = await client.post("/register", json=body(network_points=257))
    assert at_limit.status_code == 200, at_limit.text
    assert at_limit.json()["points"]["source"]["network_points"] == 256
    assert beyond.status_code == 422 and beyond.json()["errors"][0]["field"] == "network_points"


async def test_health_percentiles_cover_only_the_latest_window(serve, tiny_model):
    async with serve(settings_for(tiny_model, latency_window=10)) as (app, client):
        for _ in range(12):
            assert (await client.post("/register", json=body())).status_code == 200
        latency = (await client.get("/health")).json()["latency"]
    assert latency["count"] == 10


def test_the_latency_window_forgets_old_requests():
    from service.metrics import LatencyWindow

    window = LatencyWindow(10)
    for seconds in [0.1, 0.1] + [1e-6] * 10:
        window.add(seconds)
    summary = window.summary()
    assert summary["count"] == 10 and summary["p99_ms"] < 0.01


async def test_v2_metadata_and_health(serve, tiny_model):
    async with serve(settings_for(tiny_model)) as (app, client):
        live = await client.get("/v2/health/live")
        ready = await client.get("/v2/health/ready")
        server = await client.get("/v2")
        model = await client.get("/v2/models/object")
        model_ready = await client.get("/v2/models/object/ready")
        missing = await client.get("/v2/models/pointnet")
    assert live.json() == {"live": True} and ready.json() == {"ready": True} and model_ready.status_code == 200
    assert server.json()["name"] == "ifnet-serve"
    metadata = model.json()
    assert metadata["name"] == "object" and metadata["versions"] == ["0" * 12]
    assert metadata["inputs"] == [
        {"name": "source", "datatype": "FP32", "shape": [-1, -1, 3]},
        {"name": "target", "datatype": "FP32", "shape": [-1, -1, 3]},
    ]
    assert metadata["outputs"] == [
        {"name": "rotation", "datatype": "FP32", "shape": [-1, 3, 3]},
        {"name": "translation", "datatype": "FP32", "shape": [-1, 3]},
    ]
    assert metadata["parameters"]["network_points"] == 64
    assert missing.status_code == 404 and "pointnet" in missing.json()["error"]


async def test_v2_infer_matches_register_for_each_pair_of_a_batch(serve, tiny_model):
    sources = np.stack([SOURCE, SOURCE * 2.0, SOURCE + 1.0]).astype(np.float32)
    targets = np.stack([TARGET, TARGET[::-1] * 2.0, TARGET - 3.0]).astype(np.float32)
    request = {
        "id": "batch-1",
        "parameters": {"seed": 2},
        "inputs": [v2_tensor("source", sources), v2_tensor("target", targets)],
    }
    async with serve(settings_for(tiny_model)) as (app, client):
        response = await client.post("/v2/models/object/infer", json=request)
        expected = [
            (
                await client.post(
                    "/register", json=body(source=s.astype(np.float64), target=t.astype(np.float64), seed=2)
                )
            ).json()
            for s, t in zip(sources, targets, strict=True)
        ]
    assert response.status_code == 200, response.text
    answer = response.json()
    assert answer["id"] == "batch-1" and answer["model_name"] == "object"
    outputs = {output["name"]: output for output in answer["outputs"]}
    assert outputs["rotation"]["shape"] == [3, 3, 3] and outputs["translation"]["shape"] == [3, 3]
    rotations = np.asarray(outputs["rotation"]["data"]).reshape(3, 3, 3)
    translations = np.asarray(outputs["translation"]["data"]).reshape(3, 3)
    for index, reference in enumerate(expected):
        np.testing.assert_allclose(rotations[index], reference["rotation"], atol=1e-6)
        np.testing.assert_allclose(translations[index], reference["translation"], rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize(
    ("inputs", "message"),
    [
        ([v2_tensor("source", SOURCE[None])], "target: missing input tensor"),
        ([{**v2_tensor("source", SOURCE[None]), "datatype": "FP64"}, v2_tensor("target", TARGET[None])], "FP32"),
        ([{**v2_tensor("source", SOURCE[None]), "shape": [1, 120, 2]}, v2_tensor("target", TARGET[None])], "shape"),
        (
            [{**v2_tensor("source", SOURCE[None]), "shape": [1, 100, 3]}, v2_tensor("target", TARGET[None])],
            "360 values",
        ),
        ([v2_tensor("source", np.stack([SOURCE, SOURCE])), v2_tensor("target", TARGET[None])], "batch size"),
        (
            [
                v2_tensor("source", np.stack([SOURCE, np.ones_like(SOURCE)])),
                v2_tensor("target", np.stack([TARGET] * 2)),
            ],
            r"source[1]: is degenerate",
        ),  # fmt: skip
        (
            [{**v2_tensor("source", SOURCE[None]), "data": [float("nan")] * 360}, v2_tensor("target", TARGET[None])],
            "source: 120 point(s) have NaN or infinite coordinates",
        ),
        (
            [{**v2_tensor("source", SOURCE[None]), "data": [1e39] * 360}, v2_tensor("target", TARGET[None])],
            "source: has coordinates beyond",
        ),
        ([v2_tensor("source", np.stack([SOURCE] * 9)), v2_tensor("target", np.stack([TARGET] * 9))], "at most 8"),
    ],
    ids=[
        "missing-target",
        "datatype",
        "shape",
        "size",
        "batch-mismatch",
        "names-the-pair",
        "nan",
        "beyond-fp32",
        "batch-beyond-the-queue",
    ],
)
async def test_v2_errors_use_the_v2_error_format(serve, tiny_model, inputs, message):
    async with serve(settings_for(tiny_model, max_queue_size=8)) as (app, client):
        request = json.dumps({"inputs": inputs})
        response = await client.post("/v2/models/object/infer", content=request, headers=JSON_HEADERS)
    assert response.status_code == 422, response.text
    assert set(response.json()) == {"error"} and message in response.json()["error"]


async def test_v2_infer_on_the_shipped_model_matches_register(serve, shipped_model):
    """The real network (N=64 to stay fast): /register and v2 give the same transform."""
    request = {
        "parameters": {"network_points": 64},
        "inputs": [
            v2_tensor("source", SOURCE[None].astype(np.float32)),
            v2_tensor("target", TARGET[None].astype(np.float32)),
        ],
    }
    async with serve(settings_for(shipped_model, max_batch_size=1, warmup=False)) as (app, client):
        v2 = await client.post("/v2/models/object/infer", json=request)
        reference = await client.post(
            "/register",
            json=body(
                SOURCE.astype(np.float32).astype(np.float64),
                TARGET.astype(np.float32).astype(np.float64),
                network_points=64,
            ),
        )
    assert v2.status_code == reference.status_code == 200
    outputs = {output["name"]: np.asarray(output["data"]) for output in v2.json()["outputs"]}
    np.testing.assert_allclose(outputs["rotation"].reshape(3, 3), reference.json()["rotation"], atol=1e-6)
    np.testing.assert_allclose(outputs["translation"], reference.json()["translation"], atol=1e-5)
    assert math.isfinite(reference.json()["fitness"])


async def test_a_request_alone_refines_on_every_thread(serve, tiny_model, monkeypatch):
    """small_gicp gets the worker's threads for the check's clouds when no other request is in
    flight, as a lone model call does; one thread beside others."""
    from service import registration

    threads_used = []

    class Recording(registration.AlignmentClouds):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            threads_used.append(self.threads)

    monkeypatch.setattr(registration, "AlignmentClouds", Recording)
    cloud = np.random.default_rng(3).normal(size=(300, 3))
    limits = {"threads": 2, "workers": 1}
    async with serve(settings_for(tiny_model, **limits)) as (app, client):
        response = await client.post("/register", json=body(cloud, cloud + 0.1, method="ifnet"))
        assert response.status_code == 200, response.text
        app.state.service.in_flight += 1  # another request under way
        response = await client.post("/register", json=body(cloud, cloud + 0.1, method="ifnet"))
        app.state.service.in_flight -= 1
        assert response.status_code == 200, response.text
    assert threads_used == [2, 1]
