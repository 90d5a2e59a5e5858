"""Where the time of one ONNX Runtime call goes: kernel time by block type and by operator type.

Runs the served model (`service/models/ifnet.onnx` by default) under ONNX Runtime's profiler
(SessionOptions.enable_profiling) with the service's session settings, drops the warm-up calls,
and adds up the kernel time of every node by the IFNet module the exporter named it after
(EdgeConv, FeedbackTransformer, MatchingMatrix, OverlapPredictor, the FRB's own ops: kNN graphs,
geometry descriptor and weighted Procrustes, and the top-level loop) and by ONNX operator type.

    python bench/profile_model.py                       # batch 1, 768 points, 20 profiled calls
    python bench/profile_model.py --batch 4 --points 1024 --runs 10

Writes docs/benchmarks/profile.json (read by bench/report.py).
"""

import argparse
import json
import re
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnxruntime as ort

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from model.artifacts import file_sha256  # noqa: E402

DEFAULT_MODEL = ROOT / "service" / "models" / "ifnet.onnx"

BLOCK_TYPES = [
    ("EdgeConv", re.compile(r"/edgeconv(_\d+)?/")),
    ("FeedbackTransformer", re.compile(r"/feedback_transformer(_\d+)?/")),
    ("MatchingMatrix", re.compile(r"/matching_matrix(_\d+)?/")),
    ("OverlapPredictor", re.compile(r"/overlap_predictor(_\d+)?/")),
    ("FRB ops: kNN, descriptor, weighted Procrustes", re.compile(r"^/model/block(_\d+)?/[^/]+$")),
    ("top level: graphs, composing transforms", re.compile(r"^/model/[^/]+$")),
]
UNATTRIBUTED = "unattributed (nodes renamed by graph fusion)"


def block_type(node: str) -> str:
    for name, pattern in BLOCK_TYPES:
        if pattern.search(node):
            return name
    return UNATTRIBUTED


def session(model: Path, threads: int, profile_prefix: str | None) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    if profile_prefix:
        options.enable_profiling = True
        options.profile_file_prefix = profile_prefix
    return ort.InferenceSession(str(model), options, providers=["CPUExecutionProvider"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--points", type=int, default=768)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "profile.json")
    args = parser.parse_args()
    if not 1 <= args.runs <= 200:
        parser.error("--runs must be in [1, 200]")

    rng = np.random.default_rng(0)
    clouds = rng.normal(size=(2, args.batch, args.points, 3)).astype(np.float32)
    clouds /= np.linalg.norm(clouds, axis=-1, keepdims=True).max()
    feeds = {"source": clouds[0], "target": clouds[1]}

    plain = session(args.model, args.threads, None)  # the same call without the profiler's overhead
    for _ in range(args.warmup):
        plain.run(None, feeds)
    times = []
    for _ in range(args.runs):
        started = time.perf_counter()
        plain.run(None, feeds)
        times.append(time.perf_counter() - started)

    with tempfile.TemporaryDirectory() as tmp:
        profiled = session(args.model, args.threads, str(Path(tmp) / "ort"))
        for _ in range(args.warmup + args.runs):
            profiled.run(None, feeds)
        events = json.loads(Path(profiled.end_profiling()).read_text())

    runs = sorted((e for e in events if e.get("cat") == "Session" and e["name"] == "model_run"), key=lambda e: e["ts"])
    measured = runs[args.warmup :]
    windows = [(e["ts"], e["ts"] + e["dur"]) for e in measured]
    by_block: dict[str, float] = defaultdict(float)
    by_op: dict[str, float] = defaultdict(float)
    nodes = 0
    for event in events:
        if event.get("cat") != "Node" or not event["name"].endswith("_kernel_time"):
            continue
        if not any(start <= event["ts"] <= end for start, end in windows):
            continue
        nodes += 1
        microseconds = float(event["dur"])
        by_block[block_type(event["name"][: -len("_kernel_time")])] += microseconds
        by_op[event["args"].get("op_name", "?")] += microseconds
    kernel_total = sum(by_block.values())
    run_total = sum(e["dur"] for e in measured)

    def table(values: dict[str, float]) -> list[dict]:
        rows = sorted(values.items(), key=lambda item: -item[1])
        return [
            {"name": name, "ms_per_call": us / 1000 / len(measured), "share": us / kernel_total} for name, us in rows
        ]

    metadata = dict(plain.get_modelmeta().custom_metadata_map)
    record = {
        "command": " ".join(["python bench/profile_model.py", *sys.argv[1:]]),
        "model_version": (metadata.get("weights_sha256") or file_sha256(args.model))[:12],
        "preset": metadata.get("preset"),
        "model": str(args.model.relative_to(ROOT) if args.model.is_relative_to(ROOT) else args.model),
        "batch": args.batch,
        "points": args.points,
        "threads": args.threads,
        "runs": len(measured),
        "ms_per_call_unprofiled_median": 1000 * float(np.median(times)),
        "ms_per_call_profiled_mean": run_total / 1000 / len(measured),
        "kernel_share_of_run": kernel_total / run_total,
        "nodes_per_call": nodes / len(measured),
        "by_block_type": table(by_block),
        "by_op_type": table(by_op),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1))
    print(
        f"{record['ms_per_call_unprofiled_median']:.1f} ms per call (median, unprofiled); "
        f"{record['ms_per_call_profiled_mean']:.1f} ms profiled, of which kernels {record['kernel_share_of_run']:.0%}"
    )
    for title, rows in (("block type", record["by_block_type"]), ("operator", record["by_op_type"][:12])):
        print(f"\n{title:50s}  ms/call  share")
        for row in rows:
            print(f"{row['name']:50s}  {row['ms_per_call']:7.2f}  {row['share']:5.1%}")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
