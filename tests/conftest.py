"""Shared test fixtures (the real scans, the shipped model, a tiny ONNX model for the service) and
plain helpers the test modules import: free_port, asgi_scope, service_process."""

import asyncio
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
REAL_SCANS = SHARED_DATA / "real_scans.npz"
SHIPPED_MODEL = REPO / "service" / "models" / "object.onnx"
TINY_MODEL_POINTS = 64


def pytest_configure(config):
    """The service's tests run the network path unless they ask for another: the tiny test model's
    answers always fail the check, and the global path would multiply every request's model calls.
    Tests of `auto` and `global` name the method (or set IFNET_DEFAULT_METHOD) themselves. They also
    match features in the worker unless they ask for its child process (test_faults.py): a child
    spawned at each of the many apps' starts added over a minute to the run, and stand-ins for
    feature matching reach it only in the worker."""
    os.environ["IFNET_DEFAULT_METHOD"] = "ifnet"
    os.environ["IFNET_ISOLATE_FEATURE_MATCHING"] = "false"


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


@pytest.fixture(scope="session")
def real_scans() -> dict[str, np.ndarray]:
    """The real sensor scans of ../shared/data (float64), skipping where the data is absent."""
    if not REAL_SCANS.is_file():
        pytest.skip(f"real scans not found at {REAL_SCANS} (shared data is not checked out here)")
    with np.load(REAL_SCANS, allow_pickle=False) as archive:
        return {name: archive[name].astype(np.float64) for name in archive.files}


@pytest.fixture(scope="session")
def shipped_model() -> Path:
    if not SHIPPED_MODEL.is_file():
        pytest.skip(f"no model at {SHIPPED_MODEL}")
    return SHIPPED_MODEL


def build_tiny_model(path: Path, with_metadata: bool = True) -> Path:
    """An ONNX model with IFNet's inputs and outputs that runs in microseconds.

    rotation = identity (for every pair), translation = per-axis max of target minus that of
    source: each pair's answer depends on its own clouds only, so a batch that mixed pairs up
    would give wrong answers.
    """
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [
            helper.make_node("ReduceMax", ["target"], ["target_max"], axes=[1], keepdims=0),
            helper.make_node("ReduceMax", ["source"], ["source_max"], axes=[1], keepdims=0),
            helper.make_node("Sub", ["target_max", "source_max"], ["translation"]),
            helper.make_node("ReduceSum", ["source", "all_axes"], ["source_sum"], keepdims=1),
            helper.make_node("Mul", ["source_sum", "zero"], ["zeros"]),
            helper.make_node("Add", ["eye", "zeros"], ["rotation"]),
        ],
        "tiny_registration",
        [
            helper.make_tensor_value_info("source", TensorProto.FLOAT, ["batch", "n_source", 3]),
            helper.make_tensor_value_info("target", TensorProto.FLOAT, ["batch", "n_target", 3]),
        ],
        [
            helper.make_tensor_value_info("rotation", TensorProto.FLOAT, ["batch", 3, 3]),
            helper.make_tensor_value_info("translation", TensorProto.FLOAT, ["batch", 3]),
        ],
        initializer=[
            helper.make_tensor("eye", TensorProto.FLOAT, [1, 3, 3], np.eye(3, dtype=np.float32).ravel()),
            helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0]),
            helper.make_tensor("all_axes", TensorProto.INT64, [2], [1, 2]),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if with_metadata:
        helper.set_model_props(
            model,
            {
                "model_name": "ifnet",
                "preset": "tiny-test",
                "num_points": str(TINY_MODEL_POINTS),
                "min_points": "16",
                "weights_sha256": "0" * 64,
                "opset": "17",
                "export_date": "2025-01-01",
                "config": '{"num_points": 64}',
            },
        )
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


@pytest.fixture
def tiny_model_builder():
    """build_tiny_model(path, with_metadata=True), for tests that need a variant."""
    return build_tiny_model


@pytest.fixture(scope="session")
def tiny_model(tmp_path_factory) -> Path:
    """The tiny model as `object`, the name requests without `model` use, alone in its folder."""
    return build_tiny_model(tmp_path_factory.mktemp("models") / "object.onnx")


class GatedEngine:
    """Wraps an engine; while `gate` is clear, model calls wait for it (warm-up included).

    `calls` records the batch size of every call that went through and `besides` whether it ran
    beside its callers' work; `entered` is set once a call has reached the gate, and `at_gate` is the
    batch size of the call waiting there.
    """

    def __init__(self, engine, gated: bool = True):
        self.engine = engine
        self.info = engine.info
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.calls: list[int] = []
        self.besides: list[bool] = []
        self.at_gate = 0
        if not gated:
            self.gate.set()

    def run(self, source: np.ndarray, target: np.ndarray, beside: bool = False):
        self.at_gate = len(source)
        self.entered.set()
        if not self.gate.wait(timeout=60):
            raise TimeoutError("the test never opened the gate")
        self.at_gate = 0
        self.calls.append(len(source))
        self.besides.append(beside)
        return self.engine.run(source, target, beside)


@pytest.fixture
def gated_engine():
    """GatedEngine(engine, gated=True): see the class."""
    return GatedEngine


@pytest.fixture
def serve():
    """serve(settings, engines=None, wait_ready=True): async context manager yielding (app, client).

    Runs the app's lifespan (model loading, warm-up, shutdown drain) around an httpx client
    that talks to it in-process.
    """
    import httpx

    from service.app import create_app

    @asynccontextmanager
    async def running(settings, engines=None, wait_ready: bool = True):
        app = create_app(settings, engines=engines)
        async with app.router.lifespan_context(app):
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://testserver", timeout=60) as client:
                if wait_ready:
                    await asyncio.wait_for(app.state.service.ready.wait(), timeout=60)
                yield app, client

    return running


# ---------------------------------------------------------------- plain helpers (import from conftest)


def register_head(body: bytes) -> bytes:
    """The raw HTTP/1.1 head of a JSON POST /register carrying `body`, for tests that write to a socket."""
    return (
        f"POST /register HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def metric_values(text: str) -> dict[tuple, float]:
    """Prometheus text as {(sample name, *sorted (label, value) pairs): value}."""
    from prometheus_client.parser import text_string_to_metric_families

    return {
        (sample.name, *sorted(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


def asgi_scope(path: str, headers: dict[str, str], method: str = "POST") -> dict:
    return {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": [(key.lower().encode(), value.encode()) for key, value in headers.items()],
        "client": ("127.0.0.1", 50000),
        "server": ("testserver", 80),
    }


@contextmanager
def service_process(tmp_path: Path, model: Path, env: dict[str, str] | None = None, **settings: str):
    """A real `python -m service` on a free loopback port, awaited until ready; yields (process,
    url, log path) and stops it at the end. One worker unless `workers` says otherwise, so that
    /health speaks for the whole service."""
    import httpx

    settings.setdefault("workers", "1")
    port = free_port()
    log = tmp_path / f"service-{port}.log"
    env = {**os.environ, "PYTHONPATH": str(REPO), **(env or {})}
    env.update({f"IFNET_{key.upper()}": value for key, value in settings.items()})
    command = [sys.executable, "-m", "service", "--port", str(port), "--model-path", str(model)]
    with log.open("w") as output:
        process = subprocess.Popen(command, env=env, stdout=output, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        for _ in range(600):  # hang guard: up to a minute for imports, model load and warm-up
            if process.poll() is not None:
                raise AssertionError(f"service exited with {process.returncode}:\n{log.read_text()}")
            try:
                if httpx.get(f"{url}/ready", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        else:
            raise AssertionError(f"service never became ready:\n{log.read_text()}")
        yield process, url, log
    finally:
        if process.poll() is None:
            process.terminate()
            process.wait(timeout=60)


def kabsch(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares rigid motion between corresponding points (the "perfect network")."""
    source_centre, target_centre = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((source - source_centre).T @ (target - target_centre))
    rotation = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    return rotation, target_centre - rotation @ source_centre


def limited_reach(turned_by: list, reach_deg: float = 45.0):
    """A network that, like IFNet, only knows turns up to reach_deg: beyond, it answers "no turn"."""
    from model.geometry import rotation_angle_deg
    from service.batcher import Prediction

    async def predict(source_n, target_n):
        rotation, translation = kabsch(source_n.astype(np.float64), target_n.astype(np.float64))
        turned_by.append(float(rotation_angle_deg(rotation, np.eye(3))))
        if turned_by[-1] > reach_deg:
            return Prediction(np.eye(3), np.zeros(3), inference_ms=1.0)
        return Prediction(rotation, translation, inference_ms=1.0)

    return predict


def pipeline_inputs(
    network_points: int,
    predict,
    *,
    min_points: int = 32,
    max_cloud_points: int = 500_000,
    method: str = "ifnet",
    **options,
):
    """The options, settings and networks (one, `object`, answering with `predict`) that
    service.registration.register_clouds takes, for tests of the pipeline alone."""
    from service.registration import Network
    from service.schemas import RegistrationOptions
    from service.settings import Settings

    settings = Settings(min_points=min_points, max_cloud_points=max_cloud_points)
    options = RegistrationOptions(network_points=network_points, method=method, **options)
    return options, settings, [Network("object", network_points, predict)]


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def rendered_dom(url: str, tmp_path: Path, wait_ms: int = 15_000) -> str:
    """The page at `url` as headless Chromium renders it (scripts run), with every network request
    other than the page's own server refused, so a page that needs a CDN renders nothing."""
    if CHROMIUM is None:
        pytest.skip("Chromium is not installed (Debian package `chromium`); .ci/run installs it")
    command = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
        f"--user-data-dir={tmp_path / 'chromium-profile'}",
        f"--virtual-time-budget={wait_ms}",
        "--dump-dom",
        url,
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert done.returncode == 0, f"chromium exited {done.returncode}: {done.stderr[-2000:]}"
    return done.stdout


def assert_docs_render(base_url: str, tmp_path: Path) -> None:
    """/docs (Swagger UI) and /redoc render the API's operations in a browser without internet."""
    swagger = rendered_dom(f"{base_url}/docs", tmp_path)
    for path in ("/register", "/health", "/v2/models/{model_name}/infer"):
        assert f'data-path="{path}"' in swagger, f"Swagger UI did not render {path}"
    assert "opblock-summary-method" in swagger
    redoc = rendered_dom(f"{base_url}/redoc", tmp_path)
    for operation in ("register_register_post", "health_health_get"):
        assert f'id="operation/{operation}"' in redoc, f"ReDoc did not render {operation}"


def vanishing_request(app, body: bytes) -> tuple[asyncio.Future, asyncio.Event, list[dict]]:
    """A raw ASGI POST /register of a JSON body whose client goes away once `gone` is set:
    (the running request, gone, the messages the app sent)."""
    messages = [{"type": "http.request", "body": body, "more_body": False}]
    gone = asyncio.Event()
    sent: list[dict] = []

    async def receive():
        if messages:
            return messages.pop(0)
        await gone.wait()
        return {"type": "http.disconnect"}

    async def send(message):
        sent.append(message)

    scope = asgi_scope("/register", {"content-type": "application/json", "content-length": str(len(body))})
    return asyncio.ensure_future(app(scope, receive, send)), gone, sent
