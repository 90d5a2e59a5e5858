"""Faults: a bad model file, a pair timing out inside a running batch, feature matching crashing,
clients that vanish.

Related checks elsewhere (not repeated here): a missing model file (test_process.py and
test_engine.py), a queued pair timing out (504) and a queued client disconnecting (499)
in test_batching.py, SIGTERM with four requests in flight in test_process.py,
and SIGTERM under sustained overload in `python -m bench.load overload`.
"""

import asyncio
import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import free_port, metric_values, register_head, service_process, vanishing_request

from service.batcher import MicroBatcher, RequestTimeoutError
from service.engine import OnnxEngine
from service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
JSON = {"content-type": "application/json"}


def accepts_connections(port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(0.2)
        return probe.connect_ex(("127.0.0.1", port)) == 0


def start_and_watch(command: list[str], port: int, env: dict) -> tuple[subprocess.CompletedProcess, bool]:
    """Run a server command to its end (hang guard 120 s); also report whether the port ever answered."""
    process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    served = False
    deadline = time.monotonic() + 120
    while process.poll() is None and time.monotonic() < deadline:
        served = served or accepts_connections(port)
        time.sleep(0.05)
    if process.poll() is None:
        process.kill()
    stdout, stderr = process.communicate(timeout=30)
    return subprocess.CompletedProcess(command, process.returncode, stdout, stderr), served


# ---------------------------------------------------------------- bad model files


def corrupt_variants(tmp_path: Path, tiny_model: Path) -> dict[str, Path]:
    model = tiny_model.read_bytes()
    variants = {
        "garbage": np.random.default_rng(0).bytes(4096),
        "truncated": model[: len(model) // 2],
        "empty": b"",
        "flipped": model[:40] + bytes(255 - b for b in model[40:80]) + model[80:],
    }
    paths = {}
    for name, data in variants.items():
        paths[name] = tmp_path / f"{name}.onnx"
        paths[name].write_bytes(data)
    return paths


@pytest.mark.parametrize("variant", ["garbage", "truncated", "empty"])
def test_a_corrupt_model_stops_startup_with_a_clear_message(tmp_path, tiny_model, variant):
    path = corrupt_variants(tmp_path, tiny_model)[variant]
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    command = [sys.executable, "-m", "service", "--model-path", str(path), "--port", str(port)]
    result, served = start_and_watch(command, port, env)
    assert result.returncode == 1, result.stderr
    assert f"ifnet-serve: cannot start: model file {path} could not be loaded by onnxruntime" in result.stderr
    assert "Traceback" not in result.stderr  # a message, not a crash
    assert not served  # never a half-alive server: the port was not opened


def test_corrupt_models_are_refused_at_load_for_every_variant(tmp_path, tiny_model):
    from service.engine import ModelLoadError

    for name, path in corrupt_variants(tmp_path, tiny_model).items():
        with pytest.raises(ModelLoadError, match="could not be loaded|not an IFNet registration export") as caught:
            OnnxEngine(path)
        assert str(path) in str(caught.value), name
    with pytest.raises(ModelLoadError, match="does not exist"):
        OnnxEngine(tmp_path)  # a directory is not a model file


def test_uvicorn_factory_with_a_corrupt_model_fails_at_startup(tmp_path, tiny_model):
    """Served by uvicorn directly (not `python -m service`): the lifespan fails and uvicorn exits."""
    path = corrupt_variants(tmp_path, tiny_model)["garbage"]
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "IFNET_MODEL_PATH": str(path)}
    command = [sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app", "--port", str(port)]
    result, served = start_and_watch(command, port, env)
    assert result.returncode != 0
    assert "could not be loaded by onnxruntime" in result.stderr
    assert "Application startup failed" in result.stderr
    assert not served


# ---------------------------------------------------------------- one pair timing out inside a batch


class StepEngine:
    """Each model call waits at its own gate: the test opens them one by one."""

    def __init__(self, engine: OnnxEngine):
        self.engine = engine
        self.info = engine.info
        self.gates = [threading.Event() for _ in range(8)]
        self.calls: list[int] = []

    def run(self, source: np.ndarray, target: np.ndarray, beside: bool = False):
        index = len(self.calls)
        self.calls.append(len(source))
        if not self.gates[index].wait(timeout=60):
            raise TimeoutError("the test never opened this call's gate")
        return self.engine.run(source, target)


def clouds(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(64, 3)).astype(np.float32), rng.normal(size=(64, 3)).astype(np.float32)


async def wait_until(condition, what: str) -> None:
    for _ in range(6_000):  # hang guard, not a timing assertion
        if condition():
            return
        await asyncio.sleep(0.005)
    raise AssertionError(f"never reached: {what}")


@pytest.mark.anyio
async def test_a_pair_timing_out_mid_batch_does_not_affect_the_others(tiny_model):
    engine = StepEngine(OnnxEngine(tiny_model))
    batcher = MicroBatcher(engine, max_batch_size=4, max_queue_size=16)
    batcher.start()
    first = asyncio.ensure_future(batcher.submit(*clouds(0), timeout_s=60))
    await wait_until(lambda: engine.calls == [1], "first call running")
    # Three pairs queue behind it; the middle one will give up while their batch is running (its
    # time must not run out before the batch starts, even on a machine slowed down by other work).
    impatient = asyncio.ensure_future(batcher.submit(*clouds(1), timeout_s=2.0))
    patient = [asyncio.ensure_future(batcher.submit(*clouds(seed), timeout_s=60)) for seed in (2, 3)]
    await wait_until(lambda: batcher.queue_depth == 3, "three pairs queued")
    engine.gates[0].set()
    await wait_until(lambda: engine.calls == [1, 3], "the batch of three running")
    with pytest.raises(RequestTimeoutError):
        await impatient  # timed out while its batch was inside the model
    behind = asyncio.ensure_future(batcher.submit(*clouds(4), timeout_s=60))
    engine.gates[1].set()
    engine.gates[2].set()
    results = await asyncio.gather(first, *patient, behind)
    await batcher.close(grace_s=10)

    assert engine.calls == [1, 3, 1]
    for seed, result in zip((0, 2, 3, 4), results, strict=True):
        rotation, translation = engine.engine.run(*(cloud[None] for cloud in clouds(seed)))
        np.testing.assert_allclose(result.rotation, rotation[0], atol=1e-6)
        np.testing.assert_allclose(result.translation, translation[0], atol=1e-6)
    assert [result.batch_size for result in results] == [1, 3, 3, 1]  # the batch still counted three
    assert batcher.queue_depth == 0


# ---------------------------------------------------------------- feature matching crashing


CRASHING_POINTS = 97  # feature matching crashes on clouds of this many points (crash_on_97_points)


def crash_on_97_points(source, target, spacing, spacings):
    """feature_match, but a segfault on clouds of CRASHING_POINTS points, as native code's crash on
    the clouds it cannot handle (KISS-Matcher's on clouds far apart did, before they were moved)."""
    if len(source) == CRASHING_POINTS:
        import ctypes

        ctypes.string_at(0)  # reads address 0: SIGSEGV
    from model.geometry import feature_match

    return feature_match(source, target, spacing, spacings)


def sample_pair(points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The example table at `points` points per cloud, and its true transform."""
    from service.formats import read_cloud_file

    truth = np.loadtxt(REPO / "examples" / "true_transform.txt")
    source = read_cloud_file(REPO / "examples" / "source.ply")
    target = read_cloud_file(REPO / "examples" / "target.pcd")
    rng = np.random.default_rng(0)
    return source[rng.choice(len(source), points, replace=False)], target[: 2 * points], truth


def centres_apart(source, target, spacing, spacings):
    """A stand-in with feature_match's signature whose answer depends on every argument (KISS-Matcher's
    own answers vary a little from run to run)."""
    return np.eye(3), target.mean(axis=0) - source.mean(axis=0) + spacing * spacings


def refusing(source, target, spacing, spacings):
    raise ValueError(f"no features on {len(source)} points")


def test_feature_matchings_child_process_answers_as_the_function_would_here():
    """Its answers, and its exceptions, which leave the child serving."""
    from service.features import IsolatedFeatureMatch

    source, target, _ = sample_pair(600)
    matcher = IsolatedFeatureMatch(centres_apart)
    try:
        found = matcher(source, target, 0.01, 2.5)
        child = matcher._child
        matcher.match = refusing
        with pytest.raises(ValueError, match="no features on 600 points"):
            matcher(source, target, 0.01)
        assert matcher._child is child and child.is_alive()
    finally:
        matcher.close()
    expected = centres_apart(source, target, 0.01, 2.5)
    np.testing.assert_array_equal(found[0], expected[0])
    np.testing.assert_array_equal(found[1], expected[1])


def stuck_on_97_points(source, target, spacing, spacings):
    """centres_apart, but stuck (as native code in an endless loop) on clouds of CRASHING_POINTS points."""
    if len(source) == CRASHING_POINTS:
        time.sleep(3600)
    return centres_apart(source, target, spacing, spacings)


def test_feature_matching_stuck_in_its_child_is_killed_and_answered_as_finding_nothing(monkeypatch):
    from model.geometry import FEATURE_VOXEL_SPACINGS, point_spacing
    from service import features

    monkeypatch.setattr(features, "MAX_SECONDS", 2.0)
    failures = []
    matcher = features.IsolatedFeatureMatch(stuck_on_97_points, on_failure=failures.append)
    stuck, target, _ = sample_pair(CRASHING_POINTS)
    source, _, _ = sample_pair(600)
    spacing = max(point_spacing(source), point_spacing(target))
    try:
        matcher.start()
        first = matcher._child
        found = matcher(stuck, target, spacing)
        assert not first.is_alive() and matcher._child is None  # killed, not left running
        again = matcher(source, target, spacing)
    finally:
        matcher.close()
    assert failures == ["timeout"]
    np.testing.assert_array_equal(found[0], np.eye(3))
    np.testing.assert_array_equal(found[1], np.zeros(3))
    expected = centres_apart(source, target, spacing, FEATURE_VOXEL_SPACINGS)
    np.testing.assert_array_equal(again[1], expected[1])  # a new child's answer


HELD = []  # what holding_20_mb keeps, in the child


def holding_20_mb(source, target, spacing, spacings):
    """centres_apart, but keeping 20 MB resident per call, as KISS-Matcher keeps part of what it allocates."""
    HELD.append(np.ones(20 * 2**20 // 8))
    return centres_apart(source, target, spacing, spacings)


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads resident memory from /proc")
def test_feature_matchings_child_grown_past_its_memory_bound_is_replaced():
    """Past `max_mb` after a call, the child is replaced by a new one, off the call's time: that call
    and the next are answered, the next by a child that holds little."""
    from service import features

    source, target, _ = sample_pair(600)
    expected = centres_apart(source, target, 0.01, 2.5)
    replaced = []
    matcher = features.IsolatedFeatureMatch(holding_20_mb, on_replaced=lambda: replaced.append(1))
    try:
        answers = [matcher(source, target, 0.01, 2.5)]
        grown = matcher._child
        matcher.max_mb = features.resident_mb(grown.pid) + 30.0  # passed on the third call
        answers.append(matcher(source, target, 0.01, 2.5))
        assert replaced == [] and matcher._child is grown
        answers.append(matcher(source, target, 0.01, 2.5))
        for _ in range(600):  # hang guard: a new child is spawned and imports the matcher
            if replaced:
                break
            time.sleep(0.05)
        assert replaced == [1] and not grown.is_alive()
        answers.append(matcher(source, target, 0.01, 2.5))
        fresh = matcher._child
        assert fresh is not grown and features.resident_mb(fresh.pid) < matcher.max_mb
    finally:
        matcher.close()
    for rotation, translation in answers:
        np.testing.assert_array_equal(rotation, expected[0])
        np.testing.assert_array_equal(translation, expected[1])


@pytest.mark.anyio
async def test_a_crash_in_feature_matching_costs_the_pair_its_guess_not_the_worker(serve, shipped_model):
    """The crash happens in feature matching's child process: were it in the worker, it would end this
    test run. The pair is answered without the guess, the next one gets a new child, and /metrics
    counts the crash."""
    import multiprocessing

    from model.geometry import rotation_angle_deg

    settings = Settings(model_path=shipped_model, default_method="auto", isolate_feature_matching=True)
    crashing, _, truth = sample_pair(CRASHING_POINTS)
    source, target, _ = sample_pair(600)
    before = set(multiprocessing.active_children())  # other tests' children may still be exiting
    async with serve(settings) as (app, client):
        state = app.state.service
        state.feature_match.match = crash_on_97_points
        answers = []
        for pair in ((crashing, target), (source, target)):
            request = {"source": pair[0].tolist(), "target": pair[1].tolist(), "refine": True}
            answers.append(await client.post("/register", json=request))
        metrics = metric_values((await client.get("/metrics")).text)
        children = set(multiprocessing.active_children()) - before
    assert [answer.status_code for answer in answers] == [200, 200], answers[0].text
    failures = "ifnet_feature_matching_failures_total"
    assert metrics[(failures, ("reason", "crash"))] == 1  # not again on the second pair
    assert metrics[(failures, ("reason", "timeout"))] == 0
    for answer in answers:
        rotation = np.asarray(answer.json()["rotation"])
        assert rotation_angle_deg(rotation, truth[:3, :3]) < 2.0
    assert len(children) == 1  # the crashed child is gone, the new one serves
    for _ in range(200):  # hang guard: the app stopped, its child exits
        if not children & set(multiprocessing.active_children()):
            break
        time.sleep(0.05)
    else:
        raise AssertionError("feature matching's child process outlived the app")


def live_processes() -> dict[int, int]:
    """Every live process's parent, from /proc (zombies, which have ended, left out)."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            state, parent = stat.read_text().rsplit(")", 1)[1].split()[:2]  # after "(command name)"
        except OSError:  # gone meanwhile
            continue
        if state != "Z":
            found[int(stat.parent.name)] = int(parent)
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads the process table from /proc")
def test_feature_matchings_child_ends_with_a_worker_killed_outright(tmp_path, tiny_model):
    """SIGKILL (or the OOM killer) gives the worker no chance to stop its child: the child sees its
    parent gone and exits instead of waiting for work forever."""
    with service_process(tmp_path, tiny_model, isolate_feature_matching="true") as (process, _, _):
        # feature matching's child, and multiprocessing's resource tracker
        children = {pid for pid, parent in live_processes().items() if parent == process.pid}
        assert len(children) == 2, children
        process.kill()
        process.wait(timeout=30)
    for _ in range(200):  # hang guard: the child looks every PARENT_POLL_S
        alive = children & live_processes().keys()
        if not alive:
            break
        time.sleep(0.05)
    else:
        raise AssertionError(f"processes {alive} outlived their worker")


# ---------------------------------------------------------------- clients that vanish


def payload(seed: int, count: int = 80, **options) -> bytes:
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(count, 3))
    return json.dumps({"source": source.tolist(), "target": (source + 0.1).tolist(), **options}).encode()


@pytest.mark.anyio
async def test_a_client_leaving_while_its_batch_runs_leaves_no_stuck_work(serve, tiny_model):
    engine = StepEngine(OnnxEngine(tiny_model))
    settings = Settings(model_path=tiny_model, warmup=False, max_batch_size=4, model_calls=1)  # one batch at a time
    async with serve(settings, engines=[engine]) as (app, client):
        state = app.state.service
        blocker = asyncio.ensure_future(client.post("/register", content=payload(0), headers=JSON))
        await wait_until(lambda: engine.calls == [1], "first call running")

        leaving, gone, sent = vanishing_request(app, payload(1))
        staying = asyncio.ensure_future(client.post("/register", content=payload(2), headers=JSON))
        await wait_until(lambda: state.models["object"].batcher.queue_depth == 2, "two pairs queued")
        engine.gates[0].set()
        await wait_until(lambda: engine.calls == [1, 2], "both pairs in the running batch")
        gone.set()  # the client goes away while its pair is inside the model
        await leaving
        engine.gates[1].set()
        answers = await asyncio.gather(blocker, staying)
        engine.gates[2].set()
        after = await client.post("/register", content=payload(3), headers=JSON)
        health = (await client.get("/health")).json()
    assert sent[0]["status"] == 499
    assert [answer.status_code for answer in answers] == [200, 200]
    assert answers[1].json()["timings_ms"]["batch_size"] == 2
    assert after.status_code == 200
    assert health["in_flight"] == 0 and health["queue_depth"] == 0


def raw_request(port: int, body: bytes, send_bytes: int, wait_s: float = 0.0) -> None:
    """Send the headers and the first `send_bytes` of the body, optionally wait, then vanish."""
    head = register_head(body)
    with socket.create_connection(("127.0.0.1", port), timeout=10) as connection:
        connection.sendall(head + body[:send_bytes])
        time.sleep(wait_s)
        connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close with a reset


def test_a_real_server_forgets_clients_that_vanish(tmp_path, tiny_model):
    """uvicorn on loopback: clients that reset mid-upload or while their pair is processed."""
    heavy = payload(5, count=12_000, max_points=1024)  # parsing and sampling keep it busy for a while
    with service_process(tmp_path, tiny_model, max_network_points="1024") as (_, url, log):
        port = httpx.URL(url).port
        for index in range(3):
            raw_request(port, heavy, send_bytes=len(heavy) // 2)  # mid-upload
            raw_request(port, heavy, send_bytes=len(heavy), wait_s=0.1 * index)  # while it is processed
        with httpx.Client(base_url=url, timeout=60) as client:
            for _ in range(600):  # hang guard: in-flight work drains (threads finish, results dropped)
                health = client.get("/health").json()
                statuses = register_statuses(client.get("/metrics").text)
                if health["in_flight"] == 0 and health["queue_depth"] == 0 and sum(statuses.values()) == 6:
                    break
                time.sleep(0.1)
            else:
                raise AssertionError(f"work stuck after the clients left: {health}, answers {statuses}")
            normal = client.post("/register", content=payload(6), headers=JSON)
    text = log.read_text()
    # Every vanished client is accounted for as 499 (or 200 if it was answered before it left), none as 500.
    assert set(statuses) <= {"200", "499"}, (statuses, text[-3000:])
    assert statuses.get("499", 0) >= 3  # at least the three that left mid-upload
    assert normal.status_code == 200
    assert "Traceback" not in text and "Exception in ASGI application" not in text, text[-3000:]


def register_statuses(metrics: str) -> dict[str, int]:
    from prometheus_client.parser import text_string_to_metric_families

    counts: dict[str, int] = {}
    for family in text_string_to_metric_families(metrics):
        for sample in family.samples:
            if sample.name == "ifnet_http_requests_total" and sample.labels.get("route") == "/register":
                counts[sample.labels["status"]] = counts.get(sample.labels["status"], 0) + int(sample.value)
    return counts
