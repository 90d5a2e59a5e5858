"""The project's shipped artefacts: where the weights and the served ONNX file live, the one file
checksum that weights records, ONNX metadata and the service agree on, and an ONNX Runtime
session for checks and evaluation. Torch-free."""

import hashlib
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_WEIGHTS = PROJECT_ROOT / "model" / "weights" / "ifnet-fast.pt"
SERVED_MODEL = PROJECT_ROOT / "service" / "models" / "object.onnx"


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with Path(path).open("rb") as stream:
        for chunk in iter(lambda: stream.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def ort_session(path: Path, threads: int = 2):
    """An ONNX Runtime CPU session with every graph optimisation, for checks and evaluation."""
    import onnxruntime as ort  # heavy import, kept out of callers that only need the paths

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def network_points(session) -> int:
    """The point count a session's network was trained at (its `num_points` metadata; 768 for files
    exported before it was recorded): clouds are sampled down to it."""
    return int(session.get_modelmeta().custom_metadata_map.get("num_points", 768))
