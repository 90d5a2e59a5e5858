"""The model repository: every ONNX file of a folder served under its name, the `model` option,
`auto` asking the other models in turn, per-model routes, health and metrics, shared model-call
slots, and a repository that cannot be served refusing to start.

Two tiny models stand in for the scene models: `object` and `indoor`, the same graph exported for
64 and 32 points per cloud, so that an answer's point counts show which network ran.
"""

import asyncio
import dataclasses
import io
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_MODEL_POINTS, free_port, metric_values

from service.app import create_app
from service.engine import ModelLoadError, OnnxEngine, load_models, model_files
from service.settings import Settings

pytestmark = pytest.mark.anyio

REPO = Path(__file__).resolve().parents[2]
INDOOR_POINTS = 32
RNG = np.random.default_rng(11)
SOURCE = RNG.normal(size=(1500, 3))
SOURCE = SOURCE / np.linalg.norm(SOURCE, axis=1, keepdims=True) * [1.0, 0.6, 0.3]  # a shell, bent so that
SOURCE[:, 1:] += 0.4 * SOURCE[:, :1] ** 2  # no turn lays it on itself
TARGET = SOURCE + [0.3, -0.2, 0.1]  # a pure shift: the tiny model's answer to it is right
QUARTER_TURN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.float32)


def body(**options) -> dict:
    return {"source": SOURCE.tolist(), "target": TARGET.tolist(), **options}


def with_points(path: Path, points: int, **config) -> Path:
    """The ONNX file at `path` with its `num_points` metadata set to `points` (and its config's entries to `config`)."""
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(path))
    properties = {prop.key: prop for prop in model.metadata_props}
    properties["num_points"].value = str(points)
    properties["config"].value = json.dumps({**json.loads(properties["config"].value), **config})
    onnx.save(model, str(path))
    return path


@pytest.fixture
def repository(tmp_path, tiny_model) -> Path:
    folder = tmp_path / "models"
    folder.mkdir()
    shutil.copy(tiny_model, folder / "object.onnx")
    with_points(shutil.copy(tiny_model, folder / "indoor.onnx"), INDOOR_POINTS)
    (folder / "README.txt").write_text("not a model")
    return folder


# ---------------------------------------------------------------- the folder


def test_every_onnx_file_is_a_model_object_first_then_by_name(repository, tiny_model):
    shutil.copy(tiny_model, repository / "attic.onnx")
    assert [path.name for path in model_files(Settings(model_repository=repository))] == [
        "object.onnx",
        "attic.onnx",
        "indoor.onnx",
    ]
    alone = repository / "attic.onnx"
    assert model_files(Settings(model_repository=repository, model_path=alone)) == [alone]


def test_a_repository_that_cannot_be_served_says_what_to_do(tmp_path, tiny_model):
    with pytest.raises(ModelLoadError, match=r"holds no \.onnx file: put an IFNet ONNX export there"):
        model_files(Settings(model_repository=tmp_path))
    with pytest.raises(ModelLoadError, match="is not a folder: set IFNET_MODEL_REPOSITORY"):
        model_files(Settings(model_repository=tmp_path / "nowhere"))
    for name in ("indoor", "outdoor"):
        shutil.copy(tiny_model, tmp_path / f"{name}.onnx")
    with pytest.raises(ModelLoadError, match=r"has no object\.onnx, the model of requests that name none"):
        model_files(Settings(model_repository=tmp_path))


def test_a_broken_file_fails_the_whole_repository(repository):
    (repository / "outdoor.onnx").write_bytes(b"\x08\x07 not a protobuf" * 10)
    with pytest.raises(ModelLoadError, match=f"model file {repository / 'outdoor.onnx'} could not be loaded"):
        load_models(Settings(model_repository=repository, threads=1))


@pytest.mark.parametrize("broken", ["outdoor.onnx", None])
def test_the_service_refuses_to_start_on_a_repository_it_cannot_serve(repository, broken):
    """A broken file among good ones, or an empty folder: the log names the file or the folder and the
    port never opens (`python -m service` loads the models before binding it)."""
    if broken:
        (repository / broken).write_bytes(b"\x08\x07 not a protobuf" * 10)
    else:
        for path in repository.glob("*.onnx"):
            path.unlink()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    command = [sys.executable, "-m", "service", "--model-repository", str(repository), "--port", str(free_port())]
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    if broken:
        assert f"cannot start: model file {repository / broken} could not be loaded by onnxruntime" in result.stderr
    else:
        assert f"cannot start: model repository {repository} holds no .onnx file: put an" in result.stderr


async def test_the_app_does_not_start_on_a_broken_repository(repository):
    (repository / "outdoor.onnx").write_bytes(b"")
    app = create_app(Settings(model_repository=repository))
    with pytest.raises(ModelLoadError, match="outdoor.onnx could not be loaded"):
        async with app.router.lifespan_context(app):
            pass
    assert app.state.service.models == {}  # nothing half-loaded


# ---------------------------------------------------------------- routes and the option


async def test_each_model_is_listed_described_and_run_by_name(serve, repository):
    async with serve(Settings(model_repository=repository, max_batch_size=2)) as (app, client):
        listed = (await client.get("/v2/models")).json()
        indoor = (await client.get("/v2/models/indoor")).json()
        indoor_ready = await client.get("/v2/models/indoor/ready")
        missing = await client.get("/v2/models/outdoor")
        v2 = {"inputs": [{"name": name, "shape": list(cloud.shape), "datatype": "FP32", "data": cloud.ravel().tolist()}
                         for name, cloud in (("source", SOURCE), ("target", TARGET))]}  # fmt: skip
        inferred = (await client.post("/v2/models/indoor/infer", json=v2)).json()
        crossed = await client.post("/v2/models/indoor/infer", json={**v2, "parameters": {"model": "object"}})
        unknown_method = await client.post("/v2/models/indoor/infer", json={**v2, "parameters": {"method": "fast"}})
    assert listed == {
        "models": [
            {"name": "object", "version": "0" * 12, "ready": True},
            {"name": "indoor", "version": "0" * 12, "ready": True},
        ]
    }
    assert indoor["name"] == "indoor" and indoor["parameters"]["network_points"] == INDOOR_POINTS
    assert indoor_ready.status_code == 200
    assert missing.status_code == 404 and missing.json() == {
        "error": "model 'outdoor' is not served here; this server serves ['object', 'indoor']"
    }
    assert inferred["model_name"] == "indoor"
    np.testing.assert_allclose(np.reshape(inferred["outputs"][1]["data"], 3), [0.3, -0.2, 0.1], atol=1e-5)
    assert crossed.status_code == 422 and "model: is 'object' in the parameters but 'indoor'" in crossed.json()["error"]
    assert unknown_method.status_code == 422 and "parameters.method: " in unknown_method.json()["error"]


async def test_the_model_option_picks_the_network_in_every_body_format(serve, repository):
    options = '{"model": "indoor"}'
    npz = {"content-type": "application/x-npz"}
    archive = io.BytesIO()
    np.savez(archive, source=SOURCE, target=TARGET)
    async with serve(Settings(model_repository=repository)) as (app, client):
        default = (await client.post("/register", json=body())).json()
        as_json = (await client.post("/register", json=body(model="indoor"))).json()
        files = {"source": ("s.npy", npy(SOURCE)), "target": ("t.npy", npy(TARGET))}
        as_files = (await client.post("/register", files=files, data={"options": options})).json()
        as_npz = await client.post("/register", params={"options": options}, content=archive.getvalue(), headers=npz)
    assert (default["model"]["name"], default["points"]["source"]["network_points"]) == ("object", TINY_MODEL_POINTS)
    for answer in (as_json, as_files, as_npz.json()):
        assert (answer["model"]["name"], answer["points"]["source"]["network_points"]) == ("indoor", INDOOR_POINTS)
        assert answer["model"]["network_points"] == INDOOR_POINTS


def npy(array: np.ndarray) -> bytes:
    stream = io.BytesIO()
    np.save(stream, array)
    return stream.getvalue()


async def test_an_unknown_model_is_a_422_naming_the_field_and_the_models(serve, repository):
    async with serve(Settings(model_repository=repository)) as (app, client):
        unknown = await client.post("/register", json=body(model="outdoor"))
        empty = await client.post("/register", json=body(model=""))
    assert unknown.status_code == 422
    assert unknown.json()["errors"] == [
        {"field": "model", "problem": "is 'outdoor', not a model of this service; choose one of ['object', 'indoor']"}
    ]
    assert empty.status_code == 422 and empty.json()["errors"][0]["field"] == "model"


async def test_a_single_file_is_served_alone_under_its_name(serve, tiny_model, tmp_path):
    alone = shutil.copy(tiny_model, tmp_path / "k16.onnx")
    async with serve(Settings(model_path=alone)) as (app, client):
        listed = (await client.get("/v2/models")).json()
        answer = (await client.post("/register", json=body())).json()
    assert [model["name"] for model in listed["models"]] == ["k16"] and answer["model"]["name"] == "k16"


# ---------------------------------------------------------------- auto across the models


class Turned:
    """A model whose network answers a quarter turn off: its answers fail the check."""

    def __init__(self, engine):
        self.engine, self.info = engine, engine.info

    def run(self, source, target, beside=False):
        rotation, translation = self.engine.run(source, target)
        return rotation @ QUARTER_TURN, translation


async def test_auto_asks_the_other_models_when_the_first_answer_fails_the_check(serve, repository):
    indoor = OnnxEngine(repository / "indoor.onnx", threads=1)
    engines = [Turned(OnnxEngine(repository / "object.onnx", threads=1)), indoor]
    async with serve(Settings(model_repository=repository, warmup=False), engines=engines) as (app, client):
        network = (await client.post("/register", json=body(method="ifnet"))).json()
        auto = (await client.post("/register", json=body(method="auto"))).json()
        named = (await client.post("/register", json=body(method="auto", model="object"))).json()
        metrics = metric_values((await client.get("/metrics")).text)
    assert (network["model"]["name"], network["verified"]) == ("object", False)  # ifnet: the default model only
    assert (auto["model"]["name"], auto["stage"], auto["verified"]) == ("indoor", "ifnet", True)
    np.testing.assert_allclose(auto["translation"], [0.3, -0.2, 0.1], atol=1e-4)
    assert auto["points"]["source"]["network_points"] == INDOOR_POINTS  # its clouds, resampled for it
    assert named["model"]["name"] == "object"  # a named model's network is the only one asked
    answers = ("ifnet_answers_total", ("model", "indoor"), ("stage", "ifnet"), ("verified", "true"))
    assert metrics[answers] == 1
    inference = ("ifnet_inference_seconds_count", ("model", "indoor"))
    assert metrics[inference] == 1  # asked once, by auto; the named request never reached it


# ---------------------------------------------------------------- drafts


async def test_auto_asks_a_models_draft_and_refines_its_answer(serve, repository, tiny_model, monkeypatch):
    """`drafts/object.onnx` is `object`'s draft: `auto` asks it (its point count, refined even unasked),
    `ifnet` the model itself; it is described with the model, counted under its own label, never listed."""
    from service import registration

    # Feature matching agrees with the draft (it finds no features on these random clouds).
    monkeypatch.setattr(registration, "feature_match", lambda *args: (np.eye(3), np.array([0.3, -0.2, 0.1])))
    (repository / "drafts").mkdir()
    with_points(shutil.copy(tiny_model, repository / "drafts" / "object.onnx"), INDOOR_POINTS, time_steps=1, n_iters=1)
    # The stand-in for feature matching runs in this process (a child process would run the real one).
    async with serve(Settings(model_repository=repository, isolate_feature_matching=False)) as (app, client):
        auto = (await client.post("/register", json=body(method="auto"))).json()
        network = (await client.post("/register", json=body(method="ifnet"))).json()
        listed = (await client.get("/v2/models")).json()
        described = (await client.get("/v2/models/object")).json()["parameters"]["draft"]
        no_draft = (await client.get("/v2/models/indoor")).json()["parameters"]["draft"]
        metrics = metric_values((await client.get("/metrics")).text)
    assert (auto["model"]["name"], auto["stage"], auto["verified"]) == ("object", "draft", True)
    assert auto["points"]["source"]["network_points"] == INDOOR_POINTS and auto["refinement"] is not None
    np.testing.assert_allclose(auto["translation"], [0.3, -0.2, 0.1], atol=1e-4)
    assert auto["model"]["draft"] == described == {"version": "0" * 12, "network_points": INDOOR_POINTS, "blocks": 1}
    assert no_draft is None
    assert (network["stage"], network["points"]["source"]["network_points"]) == ("ifnet", TINY_MODEL_POINTS)
    assert network["refinement"] is None
    assert [model["name"] for model in listed["models"]] == ["object", "indoor"]
    assert metrics[("ifnet_inference_seconds_count", ("model", "object/draft"))] == 1
    assert metrics[("ifnet_inference_seconds_count", ("model", "object"))] == 1  # the ifnet request's
    assert metrics[("ifnet_answers_total", ("model", "object"), ("stage", "draft"), ("verified", "true"))] == 1


async def test_when_the_drafts_answer_and_feature_matchings_fail_auto_asks_the_model(
    serve, repository, tiny_model, monkeypatch
):
    from model.geometry import euler_to_matrix
    from service import registration

    wrong = euler_to_matrix([120.0, 0.0, 0.0])  # refined, the guess fails the check
    monkeypatch.setattr(registration, "feature_match", lambda *args: (wrong, np.zeros(3)))
    (repository / "drafts").mkdir()
    draft_file = with_points(shutil.copy(tiny_model, repository / "drafts" / "object.onnx"), INDOOR_POINTS)
    engine = OnnxEngine(repository / "object.onnx", threads=1)
    engine.draft = Turned(OnnxEngine(draft_file, threads=1, name="object/draft"))
    engines = [engine, OnnxEngine(repository / "indoor.onnx", threads=1)]
    settings = Settings(model_repository=repository, warmup=False, isolate_feature_matching=False)  # the stand-in's
    async with serve(settings, engines=engines) as (app, client):
        auto = (await client.post("/register", json=body(method="auto"))).json()
        metrics = metric_values((await client.get("/metrics")).text)
    assert (auto["model"]["name"], auto["stage"], auto["verified"]) == ("object", "ifnet", True)
    assert auto["points"]["source"]["network_points"] == TINY_MODEL_POINTS
    # The draft was asked for the source as it lies, then turned by feature matching's guess, then
    # from the 24 rotated starts that judge the model's verified answer.
    assert metrics[("ifnet_inference_seconds_count", ("model", "object/draft"))] == 2 + 24
    assert metrics[("ifnet_inference_seconds_count", ("model", "object"))] == 1
    assert (
        metrics[("ifnet_inference_seconds_count", ("model", "indoor"))] == 0
    )  # the first verified answer ends the turn


def test_a_draft_of_no_model_fails_the_whole_repository(repository, tiny_model):
    (repository / "drafts").mkdir()
    shutil.copy(tiny_model, repository / "drafts" / "outdoor.onnx")
    with pytest.raises(ModelLoadError, match=r"drafts/ holds \['outdoor.onnx'\], drafts of no model"):
        load_models(Settings(model_repository=repository, threads=1))


# ---------------------------------------------------------------- health, metrics and the CPUs


async def test_health_and_metrics_report_each_model(serve, repository):
    async with serve(Settings(model_repository=repository)) as (app, client):
        await client.post("/register", json=body(model="indoor"))
        health = (await client.get("/health")).json()
        metrics = metric_values((await client.get("/metrics")).text)
    assert health["models"] == [
        {"name": "object", "version": "0" * 12, "ready": True, "queue_depth": 0},
        {"name": "indoor", "version": "0" * 12, "ready": True, "queue_depth": 0},
    ]
    assert metrics[("ifnet_inference_seconds_count", ("model", "indoor"))] == 1
    assert metrics[("ifnet_inference_seconds_count", ("model", "object"))] == 0
    assert metrics[("ifnet_queue_depth", ("model", "object"))] == 0
    info = ("ifnet_model_info", ("model", "indoor"), ("network_points", str(INDOOR_POINTS)), ("version", "0" * 12))
    assert metrics[info] == 1


class Overlapping:
    """Counts how many calls, of every engine sharing `running`, run at once."""

    def __init__(self, info, running: dict, lock: threading.Lock):
        self.info, self.running, self.lock = info, running, lock

    def run(self, source, target, beside=False):
        with self.lock:
            self.running["now"] += 1
            self.running["most"] = max(self.running["most"], self.running["now"])
        time.sleep(0.05)
        with self.lock:
            self.running["now"] -= 1
        return np.tile(np.eye(3, dtype=np.float32), (len(source), 1, 1)), np.zeros((len(source), 3), np.float32)


async def test_the_models_share_the_model_call_slots(serve, repository):
    info = OnnxEngine(repository / "object.onnx", threads=1).info
    running, lock = {"now": 0, "most": 0}, threading.Lock()
    engines = [Overlapping(dataclasses.replace(info, name=name), running, lock) for name in ("object", "indoor")]
    settings = Settings(model_repository=repository, threads=2, model_calls=1, warmup=False)
    async with serve(settings, engines=engines) as (app, client):
        answers = await asyncio.gather(
            *(client.post("/register", json=body(model=name)) for name in ["object", "indoor"] * 3)
        )
    assert [answer.status_code for answer in answers] == [200] * 6
    assert running["most"] == 1  # one slot: a model's call never ran beside the other model's


def test_a_call_beside_another_models_call_runs_on_its_share_of_the_threads(repository):
    """The engines of a repository count each other's calls: the lone call gets every thread, a call
    of the other model started meanwhile gets threads / model_calls."""
    first, second = load_models(Settings(model_repository=repository, threads=2, model_calls=2))
    used = []

    class Recording:
        def __init__(self, session, nested):
            self.session, self.nested = session, nested

        def run(self, outputs, feeds):
            used.append(self.session.get_session_options().intra_op_num_threads)
            if self.nested:  # the other model's call starts while this one runs
                second.run(feeds["source"], feeds["target"])
            return self.session.run(outputs, feeds)

    first._sessions = [Recording(session, nested=True) for session in first._sessions]
    second._sessions = [Recording(session, nested=False) for session in second._sessions]
    cloud = np.random.default_rng(1).normal(size=(1, TINY_MODEL_POINTS, 3)).astype(np.float32)
    first.run(cloud, cloud)
    second.run(cloud, cloud)  # alone again
    assert used == [2, 1, 2]
