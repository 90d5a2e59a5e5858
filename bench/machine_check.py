"""How much of its two CPUs this machine is giving right now: one model call on 2 threads vs 1 thread.

On a shared virtual machine the second CPU can be unavailable for seconds at a time, and every
timing taken then is up to ~2x slower. This runs the served model (batch 1, its native point
count) alternately with a 2-thread and a 1-thread ONNX Runtime session for `--seconds` and
records each call, so that a benchmark run can be qualified by the state of the machine around
it. Run it before and after a set of benchmarks (`--label before` / `--label after`).

    python bench/machine_check.py --label before

Appends to docs/benchmarks/machine.json (read by bench/report.py).
"""

import argparse
import json
import os
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import onnxruntime as ort

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from model.artifacts import file_sha256  # noqa: E402

DEFAULT_MODEL = ROOT / "service" / "models" / "ifnet.onnx"


def session(model: Path, threads: int) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.intra_op_num_threads = threads
    return ort.InferenceSession(str(model), options, providers=["CPUExecutionProvider"])


def example_feeds(model: ort.InferenceSession) -> dict[str, np.ndarray]:
    """One fixed pair of random clouds (batch 1) at the model's native point count."""
    points = int(dict(model.get_modelmeta().custom_metadata_map).get("num_points", 768))
    clouds = np.random.default_rng(0).normal(size=(2, 1, points, 3)).astype(np.float32)
    clouds /= np.linalg.norm(clouds, axis=-1, keepdims=True).max()
    return {"source": clouds[0], "target": clouds[1]}


def warm_sessions(model: Path) -> tuple[ort.InferenceSession, ort.InferenceSession, dict[str, np.ndarray]]:
    """A 2-thread and a 1-thread session of model, each called once, and the feeds they ran on."""
    two, one = session(model, 2), session(model, 1)
    feeds = example_feeds(two)
    two.run(None, feeds)
    one.run(None, feeds)
    return two, one, feeds


def timed_model(model: ort.InferenceSession, path: Path) -> dict:
    """What was timed: the call's cost follows the graph (preset, EdgeConv neighbours, how it was
    exported), not the weights, so the ONNX file's own hash is recorded beside the weights'."""
    metadata = dict(model.get_modelmeta().custom_metadata_map)
    config = json.loads(metadata.get("config", "{}"))
    return {
        "version": metadata.get("weights_sha256", "")[:12] or "not recorded",
        "preset": metadata.get("preset", "not recorded"),
        "edgeconv_k": config.get("edgeconv_k"),
        "file": file_sha256(path)[:12],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--label", default="check")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "machine.json")
    args = parser.parse_args()
    if not 1 <= args.seconds <= 120:
        parser.error("--seconds must be in [1, 120]")

    two, one, feeds = warm_sessions(args.model)
    samples = []
    started = time.perf_counter()
    while time.perf_counter() - started < args.seconds:
        at = time.perf_counter()
        two.run(None, feeds)
        middle = time.perf_counter()
        one.run(None, feeds)
        samples.append((round(at - started, 2), 1000 * (middle - at), 1000 * (time.perf_counter() - middle)))
    two_ms = np.array([s[1] for s in samples])
    one_ms = np.array([s[2] for s in samples])
    ratio = one_ms / two_ms
    check = {
        "label": args.label,
        "when": datetime.now(UTC).strftime("%Y-%m-%d %H:%M:%S UTC"),
        "loadavg": os.getloadavg(),
        "pairs": len(samples),
        "two_threads_ms_median": float(np.median(two_ms)),
        "one_thread_ms_median": float(np.median(one_ms)),
        "speedup_median": float(np.median(ratio)),
        "share_second_cpu_missing": float(np.mean(ratio < 1.2)),  # 2 threads no faster than ~1
        "model": timed_model(two, args.model),
        "samples": [(t, round(a, 1), round(b, 1)) for t, a, b in samples],
    }
    checks = json.loads(args.out.read_text()) if args.out.is_file() else []
    checks.append(check)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(checks, indent=1))
    print(
        f"{args.label}: {len(samples)} calls of each; 2 threads {check['two_threads_ms_median']:.1f} ms, 1 thread "
        f"{check['one_thread_ms_median']:.1f} ms (medians); 2 threads gave < 1.2x in "
        f"{check['share_second_cpu_missing']:.0%} of the calls"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
