"""Model speed: ms per pair of eager torch and ONNX Runtime on the same weights, per preset.

    python bench/bench_model.py                       # presets paper/small/fast, random weights
    python bench/bench_model.py --presets fast --weights model/weights/ifnet-fast.pt --batches 1 4 8 --points 768 1024

Prints a table and writes docs/benchmarks/model.{md,json}. Random weights time the same
graph as trained ones. Peak RSS of the process is reported after each run.

Both runtimes compute the same evaluation-mode model (BatchNorms folded, as exported) and are
called in turn, round after round, so the machine's drifting speed (bench/machine_check.py)
reaches both alike; a short pause before each call lets the other runtime's worker threads go
idle first, since on 2 CPUs one runtime's spinning threads would slow the other's call. The
speed-up is given as the ratio of the two medians and as the median of each round's ratio; the
second compares calls made within a second of each other, so it is the one a phase change
between rounds moves least.
"""

import argparse
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from records import run_header, write_record  # noqa: E402

from export.onnx_export import DYNAMIC_AXES, RegistrationGraph, export_onnx, fold_batch_norms  # noqa: E402
from model.artifacts import ort_session  # noqa: E402
from model.checkpoint import load_checkpoint  # noqa: E402
from model.ifnet import PRESETS, IFNet, preset  # noqa: E402

PAUSE_S = 0.05


def interleaved_ms(runs: dict[str, Callable[[], object]], repeats: int) -> dict[str, list[float]]:
    """ms of every call of each run, one per round, the runs called in turn (who goes first rotates)."""
    names = list(runs)
    for run in runs.values():  # warm-up
        run()
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(repeats):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            time.sleep(PAUSE_S)
            started = time.perf_counter()
            runs[name]()
            times[name].append(1000 * (time.perf_counter() - started))
    return times


def paired_speedups(ort_ms: list[float], eager_ms: list[float]) -> list[float]:
    """eager / ORT time of each round: the two calls ran back to back, so a change of the
    machine's speed between rounds (bench/machine_check.py) cancels out of each ratio."""
    return [eager / ort for ort, eager in zip(ort_ms, eager_ms, strict=True)]


def train_step_seconds(model: IFNet, steps: int, n: int) -> float:
    """Median seconds of one Adam step (forward, the three losses, backward) at batch 4."""
    from model.training.losses import ifnet_losses

    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    source, target = torch.rand(4, n, 3) - 0.5, torch.rand(4, n, 3) - 0.5

    def step() -> None:
        loss = ifnet_losses(model(source, target), target, model.config).total
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    seconds = float(np.median(interleaved_ms({"step": step}, steps)["step"])) / 1000
    model.eval()
    return seconds


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", nargs="+", default=["paper", "small", "fast"], choices=sorted(PRESETS))
    parser.add_argument("--weights", type=Path, help="trained weights (only with a single preset)")
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--points", nargs="+", type=int, default=[768])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-eager", action="store_true")
    parser.add_argument("--train-steps", type=int, default=0, help="also time this many training steps (batch 4)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "model")
    args = parser.parse_args()
    if args.weights and len(args.presets) != 1:
        parser.error("--weights holds one model: give the one --presets it was trained as")
    torch.set_num_threads(args.threads)

    rows = []
    for name in args.presets:
        if args.weights:
            model = load_checkpoint(args.weights).model
        else:
            torch.manual_seed(0)
            model = IFNet(preset(name)).eval()
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "model.onnx"
            n0 = model.config.num_points
            export_seconds = export_onnx(
                RegistrationGraph(model),
                path,
                (torch.rand(1, n0, 3), torch.rand(1, n0, 3)),
                ["source", "target"],
                ["rotation", "translation"],
                DYNAMIC_AXES,
            )
            size_mb = path.stat().st_size / 1e6
            session = ort_session(path, args.threads)
            eager_model = fold_batch_norms(model)  # the arithmetic the ONNX graph runs
            step_s = train_step_seconds(model, args.train_steps, n0) if args.train_steps else float("nan")
            for n in args.points:
                for batch in args.batches:
                    source = np.random.rand(batch, n, 3).astype(np.float32) - 0.5
                    target = np.random.rand(batch, n, 3).astype(np.float32) - 0.5
                    feeds = {"source": source, "target": target}
                    runs = {"ort": lambda s=session, f=feeds: s.run(None, f)}
                    if not args.skip_eager:
                        s, t = torch.from_numpy(source), torch.from_numpy(target)
                        runs["eager"] = lambda m=eager_model, s=s, t=t: m(s, t)
                    with torch.no_grad():
                        times = interleaved_ms(runs, args.repeats)
                    ort_ms = float(np.median(times["ort"]))
                    eager_ms = float(np.median(times["eager"])) if "eager" in times else float("nan")
                    paired = paired_speedups(times["ort"], times["eager"]) if "eager" in times else [float("nan")]
                    row = {
                        "preset": name,
                        "parameters": model.num_parameters(),
                        "points": n,
                        "batch": batch,
                        "ort_ms_per_pair": ort_ms / batch,
                        "eager_ms_per_pair": eager_ms / batch,
                        "speedup": eager_ms / ort_ms,
                        "speedup_paired": float(np.median(paired)),
                        "speedup_paired_range": [min(paired), max(paired)],
                        "onnx_mb": size_mb,
                        "export_s": export_seconds,
                        "peak_rss_mb": peak_rss_mb(),
                        "train_step_s": step_s,
                    }
                    rows.append(row)
                    print(
                        f"{name:6s} N={n:5d} B={batch}: ORT {row['ort_ms_per_pair']:7.1f} ms/pair, eager "
                        f"{row['eager_ms_per_pair']:7.1f} ms/pair ({row['speedup']:.2f}x; per round "
                        f"{row['speedup_paired']:.2f}x, {min(paired):.2f}-{max(paired):.2f}x), peak RSS "
                        f"{row['peak_rss_mb']:.0f} MB",
                        flush=True,
                    )

    header = run_header()
    write_record(args.out.with_suffix(".json"), {**header, "threads": args.threads, "rows": rows})
    table_header = (
        "| preset | params | N | batch | ORT ms/pair | eager ms/pair | ORT speed-up | per round (range) | ONNX MB "
        "| export s | train step s (batch 4) |"
    )
    lines = [
        f"Command: `{header['command']}` ({header['when']}, {args.threads} threads, median of {args.repeats})",
        "",
        table_header,
        "|---" * 11 + "|",
    ]
    for r in rows:
        lines.append(
            f"| {r['preset']} | {r['parameters']:,} | {r['points']} | {r['batch']} | {r['ort_ms_per_pair']:.1f}"
            f" | {r['eager_ms_per_pair']:.1f} | {r['speedup']:.2f}x | {r['speedup_paired']:.2f}x "
            f"({r['speedup_paired_range'][0]:.2f}-{r['speedup_paired_range'][1]:.2f}x)"
            f" | {r['onnx_mb']:.2f} | {r['export_s']:.1f}"
            f" | {r['train_step_s']:.2f} |"
        )
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
