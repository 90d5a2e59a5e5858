"""What a distilled student could save: the ONNX call of narrower IFNets (random weights: the cost
does not depend on them), over fewer blocks and points, as the median per-pair ratio to the
shipped object network's call and to Open3D FPFH + RANSAC + ICP's whole pipeline, interleaved on
ModelNet10 test pairs. A student is worth training
only if its call is cheap enough to matter.

    PYTHONPATH=. python docs/training/experiments/student_cost.py --pairs 12
"""

import argparse
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bench import harness
from export.onnx_export import DYNAMIC_AXES, RegistrationGraph, export_onnx, metadata_for
from model.checkpoint import load_checkpoint
from model.ifnet import IFNet, IFNetConfig


def narrower(config: IFNetConfig, factor: int) -> IFNetConfig:
    """Every width of the network divided by `factor` (EdgeConv, features, attention, position)."""
    return replace(
        config,
        edgeconv_widths=tuple(max(4, width // factor) for width in config.edgeconv_widths),
        emb_dims=config.emb_dims // factor,
        attention_hidden=config.attention_hidden // factor,
        pos_hidden=max(4, config.pos_hidden // factor),
    )


def students(shipped: IFNetConfig) -> dict[str, IFNetConfig]:
    half, quarter = narrower(shipped, 2), narrower(shipped, 4)
    return {
        "shipped shape": shipped,
        "widths / 2": half,
        "widths / 4": quarter,
        "widths / 2, edgeconv_k 8": replace(half, edgeconv_k=8),
        "widths / 2, 512 points": replace(half, num_points=512),
        "widths / 2, 2 x 3 blocks": replace(half, time_steps=2),
        "widths / 2, 1 x 3 blocks": replace(half, time_steps=1),
        "widths / 2, 1 x 3, 512": replace(half, time_steps=1, num_points=512),
        "widths / 4, 2 x 3, 512": replace(quarter, time_steps=2, num_points=512),
        "widths / 2, 1 x 2, 384": replace(half, time_steps=1, n_iters=2, num_points=384),
        "shipped widths, 1 x 2, 384": replace(shipped, time_steps=1, n_iters=2, num_points=384),
    }


def export(config: IFNetConfig, path: Path) -> int:
    """A random-weight network of `config` exported as the service's graph; its parameter count."""
    model = IFNet(config).eval()
    example = tuple(torch.rand(1, config.num_points, 3) - 0.5 for _ in range(2))
    metadata = metadata_for(model, "student", "random")  # its point count, which the sampling follows
    graph = RegistrationGraph(model)
    export_onnx(graph, path, example, ["source", "target"], ["rotation", "translation"], DYNAMIC_AXES, metadata)
    return sum(parameter.numel() for parameter in model.parameters())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=12)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    torch.manual_seed(0)
    shipped = load_checkpoint(harness.ROOT / "model/weights/ifnet-fast.pt", None, None, None)[0].config
    networks, sizes = {"shipped": harness.Network(harness.MODEL)}, {}
    with tempfile.TemporaryDirectory() as folder:
        for index, (name, config) in enumerate(students(shipped).items()):
            path = Path(folder) / f"student-{index}.onnx"
            sizes[name] = export(config, path)
            networks[name] = harness.Network(path)
    pairs = harness.modelnet_pairs(args.pairs)
    feeds = {name: [net.prepare(pair.source, pair.target)[0] for pair in pairs] for name, net in networks.items()}
    for name, network in networks.items():  # first calls out of the timing
        network.call(feeds[name][0])
    ms: dict[str, list[float]] = {name: [] for name in [*networks, "open3d"]}
    for _ in range(args.rounds):
        for index, pair in enumerate(pairs):
            started = time.perf_counter()
            harness.open3d_fpfh_ransac_icp(pair.source, pair.target, pair.voxel)
            ms["open3d"].append((time.perf_counter() - started) * 1000.0)
            for name, network in networks.items():
                started = time.perf_counter()
                network.call(feeds[name][index])
                ms[name].append((time.perf_counter() - started) * 1000.0)
    shipped_ms, open3d_ms = np.array(ms["shipped"]), np.array(ms["open3d"])
    print(f"{len(pairs)} pairs x {args.rounds} rounds; median per-pair ratio to the shipped call and to Open3D")
    for name in networks:
        times = np.array(ms[name])
        ratios = f"{np.median(times / shipped_ms):5.2f}x shipped  {np.median(times / open3d_ms):5.2f}x Open3D"
        size = f"{sizes[name]:6d} parameters" if name in sizes else ""
        print(f"{ratios}  {statistics.median(ms[name]):7.1f} ms  {name:28s} {size}")
    print(f"Open3D FPFH + RANSAC + ICP: {statistics.median(ms['open3d']):.1f} ms")


if __name__ == "__main__":
    main()
