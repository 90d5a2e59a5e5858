"""The ONNX Runtime sessions behind the service: the model repository, loading, model metadata,
thread count, warm-up."""

import json
import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from model.artifacts import file_sha256
from service.cpus import available_cpus
from service.settings import Settings

logger = logging.getLogger(__name__)

REQUIRED_INPUTS = ("source", "target")
REQUIRED_OUTPUTS = ("rotation", "translation")
DEFAULT_NETWORK_POINTS = 768
ORT_TO_V2_DATATYPE = {"tensor(float)": "FP32", "tensor(double)": "FP64", "tensor(int64)": "INT64"}
DEFAULT_MODEL = "object"  # requests that name no model use it, and `auto` asks it first
# A model's draft: the same weights unrolled over fewer blocks on fewer points, in this sub-folder of
# the repository under the model's file name; `auto` asks it before the model (service/README.md, "Models").
DRAFTS = "drafts"


class ModelLoadError(RuntimeError):
    """The model file is missing, unreadable or does not follow the IFNet ONNX contract."""


@dataclass(frozen=True)
class TensorSpec:
    name: str
    datatype: str  # Open Inference Protocol name, e.g. "FP32"
    shape: list[int]  # -1 where the dimension is dynamic


@dataclass(frozen=True)
class ModelInfo:
    name: str  # the file's name without `.onnx`: how requests and routes name the model
    network_points: int  # points per cloud the network was exported for
    min_network_points: int  # fewest points per cloud the graph runs on (its widest kNN)
    file_sha256: str
    path: str
    inputs: list[TensorSpec]
    outputs: list[TensorSpec]
    preset: str | None = None
    weights_sha256: str | None = None
    opset: str | None = None
    export_date: str | None = None
    config: dict | None = None
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def version(self) -> str:
        """Short, stable identifier of the weights (of the file when the export did not record them)."""
        return (self.weights_sha256 or self.file_sha256)[:12]


class Engine(Protocol):
    """What the batcher needs from a model: metadata and one batched forward pass."""

    info: ModelInfo

    def run(self, source: np.ndarray, target: np.ndarray, beside: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """[B, N, 3] and [B, M, 3] float32 -> rotations [B, 3, 3] and translations [B, 3]; `beside`:
        the caller does CPU work of its own while the call runs."""
        ...


def _tensor_specs(nodes) -> list[TensorSpec]:
    return [
        TensorSpec(
            name=node.name,
            datatype=ORT_TO_V2_DATATYPE.get(node.type, node.type),
            shape=[dim if isinstance(dim, int) else -1 for dim in node.shape],
        )
        for node in nodes
    ]


def _metadata_count(metadata: dict[str, str], key: str, path: Path, missing: int, consequence: str) -> int:
    """A positive integer from the export's metadata; `missing` (with a warning) where it is absent."""
    value = metadata.get(key)
    if value is None:
        logger.warning("model %s has no `%s` metadata; %s %d points", path, key, consequence, missing)
        return missing
    try:
        count = int(value)
        if count < 1:
            raise ValueError
    except ValueError:
        raise ModelLoadError(f"model {path}: metadata {key}={value!r} is not a positive integer") from None
    return count


class RunningCalls:
    """This process's model calls under way, across every engine that shares this count (all of the
    service's), and its registration requests in flight (the service state counts them here)."""

    def __init__(self):
        self._count = 0
        self.requests = 0
        self._lock = threading.Lock()

    @contextmanager
    def call(self) -> Iterator[bool]:
        """Counts one call while it runs; yields whether it runs alone: no other call runs and no
        other request is in flight (whose parsing and geometry would take a CPU from its threads)."""
        with self._lock:
            alone = self._count == 0 and self.requests <= 1
            self._count += 1
        try:
            yield alone
        finally:
            with self._lock:
                self._count -= 1


class OnnxEngine:
    """The model in ONNX Runtime with graph optimisations on and intra-op threads sized to this process.

    Up to `model_calls` calls may run at once (ONNX Runtime's Run is thread-safe). A call that
    runs alone (`RunningCalls.call`) gets all `threads` (default: the usable CPUs), the lowest
    latency for a lone request; any other gets threads // (model_calls x workers), so that under
    load the calls of every worker share the CPUs out instead of their threads contending for them.
    Each thread count is its own session (a session's thread count is fixed when it opens); where
    the two counts are equal there is just one. Engines that share `running` count each other's
    calls, so that calls of several models share the CPUs out too.
    """

    def __init__(
        self,
        path: Path,
        threads: int | None = None,
        model_calls: int = 1,
        running: RunningCalls | None = None,
        name: str | None = None,
        workers: int = 1,
    ):
        path = Path(path)
        self.draft: OnnxEngine | None = None  # the model's draft (`load_models` sets it), asked by `auto`
        if not path.is_file():
            raise ModelLoadError(
                f"model file {path} does not exist: set IFNET_MODEL_PATH (or --model-path) to an IFNet ONNX export"
            )
        self.model_calls = model_calls
        self.threads = threads or available_cpus()  # of a call that runs alone
        # The other workers' calls share the CPUs too.
        self.threads_beside_others = max(1, self.threads // (model_calls * workers))
        self._sessions = [open_session(path, self.threads)]  # [alone, beside others] where the thread counts differ
        if self.threads_beside_others != self.threads:
            self._sessions.append(open_session(path, self.threads_beside_others))
        self.running = running or RunningCalls()

        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        missing_in = set(REQUIRED_INPUTS) - {node.name for node in inputs}
        missing_out = set(REQUIRED_OUTPUTS) - {node.name for node in outputs}
        if missing_in or missing_out:
            raise ModelLoadError(
                f"model file {path} is not an IFNet registration export: it lacks inputs {sorted(missing_in)} "
                f"and/or outputs {sorted(missing_out)} (has inputs {[n.name for n in inputs]}, "
                f"outputs {[n.name for n in outputs]})"
            )
        metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        if not metadata:
            logger.warning(
                "model %s has no metadata (model_name, weights_sha256, ...): is it a development export?", path
            )
        config = None
        if "config" in metadata:
            try:
                config = json.loads(metadata["config"])
            except json.JSONDecodeError:
                logger.warning("model %s: metadata `config` is not JSON; ignoring it", path)
        by_name = {spec.name: spec for spec in _tensor_specs(inputs) + _tensor_specs(outputs)}
        native = _metadata_count(metadata, "num_points", path, DEFAULT_NETWORK_POINTS, "resampling clouds to")
        # Without the record, only the count the network was exported for is known to run.
        fewest = _metadata_count(metadata, "min_points", path, native, "giving it clouds of at least")
        self.info = ModelInfo(
            name=name or path.stem,
            network_points=native,
            min_network_points=fewest,
            file_sha256=file_sha256(path),
            path=str(path),
            inputs=[by_name[name] for name in REQUIRED_INPUTS],
            outputs=[by_name[name] for name in REQUIRED_OUTPUTS],
            preset=metadata.get("preset"),
            weights_sha256=metadata.get("weights_sha256"),
            opset=metadata.get("opset"),
            export_date=metadata.get("export_date"),
            config=config,
            metadata=metadata,
        )
        logger.info(
            "loaded model %s (%s, version %s, %d native points): up to %d call(s) at once, on %d ORT threads "
            "alone and %d beside others",
            path,
            self.info.name,
            self.info.version,
            self.info.network_points,
            self.model_calls,
            self.threads,
            self.threads_beside_others,
        )

    @property
    def session(self):
        """The session of a call that runs alone (all `threads`); every session has its inputs and metadata."""
        return self._sessions[0]

    def run(self, source: np.ndarray, target: np.ndarray, beside: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The call on all `threads` where it runs alone, else (or `beside` its caller's own work) on
        the threads of a call beside others."""
        with self.running.call() as alone:
            return self._run(self._sessions[0] if alone and not beside else self._sessions[-1], source, target)

    def warm_up(self, source: np.ndarray, target: np.ndarray) -> None:
        """One call on every session, so that neither pays its first-call cost on a request."""
        for session in self._sessions:
            self._run(session, source, target)

    @staticmethod
    def _run(session, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rotation, translation = session.run(
            list(REQUIRED_OUTPUTS),
            {"source": np.ascontiguousarray(source, np.float32), "target": np.ascontiguousarray(target, np.float32)},
        )
        return rotation, translation


def open_session(path: Path, threads: int):
    """An ONNX Runtime session of the model file on `threads` intra-op threads, as the service runs it."""
    import onnxruntime as ort  # heavy import, kept out of modules that only need the types above

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1  # the graph is one chain; calls run side by side instead
    # Its threads stop spinning when a call ends: spinning on, they would take the CPUs that the
    # refinement and the check, run right after the call, want.
    options.add_session_config_entry("session.force_spinning_stop", "1")
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own exception types for corrupt files
        raise ModelLoadError(f"model file {path} could not be loaded by onnxruntime: {error}") from error


def model_files(settings: Settings) -> list[Path]:
    """The files to serve, in the order `auto` asks them: IFNET_MODEL_PATH alone, else every `*.onnx`
    file of the repository folder, `object.onnx` first and the others by name."""
    if settings.model_path is not None:
        return [settings.model_path]
    folder = settings.model_repository
    if not folder.is_dir():
        raise ModelLoadError(
            f"model repository {folder} is not a folder: set IFNET_MODEL_REPOSITORY (or --model-repository) to the "
            "folder of the ONNX models"
        )
    files = sorted(folder.glob("*.onnx"), key=lambda path: (path.stem != DEFAULT_MODEL, path.stem))
    if not files:
        raise ModelLoadError(
            f"model repository {folder} holds no .onnx file: put an IFNet ONNX export there "
            f"(`python -m export --output {folder / DEFAULT_MODEL}.onnx`) or point IFNET_MODEL_REPOSITORY elsewhere"
        )
    if len(files) > 1 and files[0].stem != DEFAULT_MODEL:
        raise ModelLoadError(
            f"model repository {folder} has no {DEFAULT_MODEL}.onnx, the model of requests that name none: add it, "
            "or serve one file alone with IFNET_MODEL_PATH"
        )
    return files


def draft_file(model_file: Path) -> Path:
    """Where a model's draft lives: `drafts/<model's file name>` beside the model's file."""
    return model_file.parent / DRAFTS / model_file.name


def load_models(settings: Settings) -> list[OnnxEngine]:
    """One engine per model file, in `model_files`' order, each with its draft's engine when the
    repository has one, all or none: the first file that fails raises ModelLoadError with its path
    and reason, as does a draft of no model. The engines share one count of running calls."""
    running = RunningCalls()
    files = model_files(settings)
    engines = []
    for path in files:
        engine = OnnxEngine(path, settings.threads, settings.model_calls, running, workers=settings.workers)
        if draft_file(path).is_file():
            name = f"{engine.info.name}/draft"  # its label in the batcher's metrics
            engine.draft = OnnxEngine(
                draft_file(path), settings.threads, settings.model_calls, running, name, settings.workers
            )
        engines.append(engine)
    if settings.model_path is None:
        strays = sorted(
            {path.name for path in (settings.model_repository / DRAFTS).glob("*.onnx")} - {f.name for f in files}
        )
        if strays:
            raise ModelLoadError(
                f"model repository {settings.model_repository}: {DRAFTS}/ holds {strays}, drafts of no model: "
                f"add the model beside them or remove them"
            )
    return engines


def warm_up_engine(engine: Engine, batch_sizes: range | list[int], network_points: int) -> None:
    """One model call at each batch size, so the first real requests pay no allocation or tuning cost."""
    rng = np.random.default_rng(0)
    for batch_size in batch_sizes:
        # Distinct random points in the unit ball: all-zero inputs would make every kNN a tie.
        points = rng.normal(size=(2, batch_size, network_points, 3)).astype(np.float32)
        points /= np.linalg.norm(points, axis=-1, keepdims=True).max()
        warm = getattr(engine, "warm_up", engine.run)  # an engine with several sessions warms each
        warm(points[0], points[1])
