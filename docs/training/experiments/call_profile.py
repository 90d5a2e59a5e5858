"""Where an ONNX call's time goes, and what exact rewrites of the exported graph save.

Profile: ONNX Runtime's kernel time per call by operator type and by the part of the block that
runs it, on ModelNet10 test pairs prepared as the service prepares them. Variants: the same weights
exported three other ways (every linear layer on 2-D rows, so that the exporter writes Gemm with its
bias; point counts fixed in the graph; point counts and a batch of one fixed), each call's outputs
compared with the shipped file's and timed interleaved with it, on one thread.

    PYTHONPATH=. python docs/training/experiments/call_profile.py service/models/drafts/object.onnx
    PYTHONPATH=. python docs/training/experiments/call_profile.py service/models/object.onnx --threads 2
    PYTHONPATH=. python docs/training/experiments/call_profile.py service/models/drafts/object.onnx --variants
"""

import argparse
import contextlib
import json
import re
import tempfile
import time
from collections import Counter
from pathlib import Path
from unittest import mock

import numpy as np
import onnxruntime as ort
import torch
import torch.nn.functional as F
from torch import nn

from bench import harness
from export.onnx_export import DYNAMIC_AXES, RegistrationGraph, export_onnx, metadata_for
from model.artifacts import DEFAULT_WEIGHTS
from model.checkpoint import load_checkpoint
from service.engine import open_session

OUTPUTS = ["rotation", "translation"]


def profiled_session(path: Path, threads: int) -> ort.InferenceSession:
    """A session as service.engine.open_session makes one, recording every node's time."""
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    options.add_session_config_entry("session.force_spinning_stop", "1")
    options.enable_profiling, options.profile_file_prefix = True, str(Path(tempfile.gettempdir()) / "ort-profile")
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def feeds_for(path: Path, pairs: int) -> list[dict]:
    network = harness.Network(path, 1)
    return [network.prepare(pair.source, pair.target)[0] for pair in harness.modelnet_pairs(pairs)]


def profile(path: Path, threads: int, feeds: list[dict], rounds: int) -> None:
    runner = profiled_session(path, threads)
    for _ in range(rounds + 1):  # the first round's calls too: a few among many
        for feed in feeds:
            runner.run(OUTPUTS, feed)
    calls = len(feeds) * (rounds + 1)
    events = json.loads(Path(runner.end_profiling()).read_text())
    kernels = [e for e in events if e.get("cat") == "Node" and e["name"].endswith("_kernel_time")]
    by_op, nodes, by_part = Counter(), Counter(), Counter()
    for event in kernels:
        op = event["args"]["op_name"]
        by_op[op] += event["dur"]
        nodes[op] += 1
        name = event["name"].removesuffix("_kernel_time").removeprefix("/model/").removeprefix("block/")
        part = re.sub(r"_\d+$", "", name.split("/")[0]) if "/" in name else "outside the modules"
        by_part[part] += event["dur"]
    total = sum(by_op.values())
    print(f"{path}: {total / calls / 1000:.1f} ms of kernel time per call, {threads} thread(s)")
    for op, spent in by_op.most_common(14):
        print(f"  {op:14s} {spent / total:6.1%}  {nodes[op] // calls:4d} nodes")
    print("  by module (outside the modules: the kNN graphs, Procrustes, composing the motions):")
    for part, spent in by_part.most_common(8):
        print(f"  {part[:40]:40s} {spent / total:6.1%}")


def linear_on_rows(self: nn.Linear, x: torch.Tensor) -> torch.Tensor:
    """nn.Linear on [..., C] as one product of [rows, C]: exported as Gemm with the bias inside."""
    rows = F.linear(x.reshape(-1, x.shape[-1]), self.weight, self.bias)
    return rows.view(*x.shape[:-1], self.weight.shape[0])


def variants(path: Path, folder: Path) -> dict[str, Path]:
    """The file's weights (ifnet-fast.pt at its blocks and point count) exported three other ways."""
    meta = open_session(path, 1).get_modelmeta().custom_metadata_map
    config = json.loads(meta["config"])
    model, sha256, preset = load_checkpoint(
        DEFAULT_WEIGHTS, config["n_iters"], config["time_steps"], config["num_points"]
    )
    if not meta["weights_sha256"].startswith(sha256):
        raise SystemExit(f"{path} was not exported from {DEFAULT_WEIGHTS}")
    n = config["num_points"]
    example = (torch.rand(1, n, 3) - 0.5, torch.rand(1, n, 3) - 0.5)
    batch_only = {name: {0: "batch"} for name in DYNAMIC_AXES}
    files = {}
    for name, axes, rows in [
        ("linear layers on 2-D rows", DYNAMIC_AXES, True),
        ("point counts fixed", batch_only, False),
        ("point counts and batch fixed", {}, False),
    ]:
        files[name] = folder / f"{len(files)}.onnx"
        with mock.patch.object(nn.Linear, "forward", linear_on_rows) if rows else contextlib.nullcontext():
            export_onnx(
                RegistrationGraph(model),
                files[name],
                example,
                ["source", "target"],
                OUTPUTS,
                axes,
                metadata_for(model, preset, sha256),
            )
    return files


def compare(path: Path, files: dict[str, Path], feeds: list[dict], rounds: int) -> None:
    runners = {"shipped": open_session(path, 1)} | {name: open_session(file, 1) for name, file in files.items()}
    expected = [runners["shipped"].run(OUTPUTS, feed) for feed in feeds]
    for name, runner in runners.items():
        got = [runner.run(OUTPUTS, feed) for feed in feeds]
        difference = max(float(np.abs(a - b).max()) for g, e in zip(got, expected) for a, b in zip(g, e))
        print(f"  {name}: max output difference from the shipped file {difference:.1e}")
    ms = {name: [] for name in runners}
    names = list(runners)
    for r in range(rounds):
        for feed in feeds:
            for name in names[r % len(names) :] + names[: r % len(names)]:
                started = time.perf_counter()
                runners[name].run(OUTPUTS, feed)
                ms[name].append((time.perf_counter() - started) * 1000.0)
    base = np.array(ms["shipped"])
    print(f"{len(feeds)} pairs x {rounds} rounds, one thread; median per-pair ratio to the shipped call")
    for name, times in ms.items():
        print(f"  {np.median(np.array(times) / base):.3f}x  {np.median(times):6.2f} ms  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--pairs", type=int, default=12)
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--variants", action="store_true", help="also export and time the three variants")
    args = parser.parse_args()
    torch.manual_seed(0)
    feeds = feeds_for(args.model, args.pairs)
    profile(args.model, args.threads, feeds, max(1, args.rounds // 3))
    if args.variants:
        with tempfile.TemporaryDirectory() as folder:
            compare(args.model, variants(args.model, Path(folder)), feeds, args.rounds)


if __name__ == "__main__":
    main()
