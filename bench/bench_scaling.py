"""Throughput at 16 clients against one client at a time, in interleaved windows.

The goal "16 clients get >= 1.5x the pairs/s of one at a time" compares two rows that
bench/bench_service.py measures minutes apart, and this 2-CPU virtual machine's speed drifts in
phases of seconds to minutes (bench/machine_check.py): one slow row flatters or sinks the ratio.
Here one service process per mode runs throughout, and short windows of 1 and of 16 closed-loop
clients alternate (the order rotating each round), so that both client counts of a round meet the
same phase; the verdict is the median of the per-round ratios.

Modes are bench_service.py's: `off` (the shipped defaults) and `1call` (one model call at a time
on every thread). Payload: JSON pairs of 768 points per cloud (the network's own size).

    python bench/bench_scaling.py                    # 6 rounds of 8-second windows, ~7 minutes
    python bench/bench_scaling.py --rounds 3 --window 5

Writes docs/benchmarks/scaling.json (read by bench/report.py). Everything stays on 127.0.0.1 and
each process is stopped with SIGTERM.
"""

import argparse
import asyncio
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import loadgen  # noqa: E402
from bench_batching import free_port, start_service, stop_service, wait_ready  # noqa: E402
from bench_service import BATCH_SIZE_ON, MODES  # noqa: E402
from records import run_header, write_record  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CLIENT_COUNTS = (1, 16)


def window(url: str, bodies: list[loadgen.Body], clients: int, seconds: float) -> dict:
    run = asyncio.run(loadgen.closed_loop(url, bodies, clients, seconds))
    summary = run.summary()
    return {"pairs_per_s": summary["pairs_per_s"], "p50_ms": summary["p50_ms"], "statuses": summary["statuses"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--modes", nargs="+", default=["off", "1call"], choices=list(MODES))
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--window", type=float, default=8.0, help="measured seconds per window")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "scaling.json")
    args = parser.parse_args()
    if not 1 <= args.rounds <= 30 or not 2 <= args.window <= 60:
        parser.error("--rounds must be in [1, 30] and --window in [2, 60]")
    if not loadgen.scans_available():
        print(f"real scans not found at {loadgen.REAL_SCANS}", file=sys.stderr)
        return 2

    bodies = loadgen.model_sized_bodies(768)
    # mode -> (max batch size, model calls at once), as bench_service.py runs them by default
    settings = {mode: (MODES[mode][0] or BATCH_SIZE_ON, MODES[mode][1]) for mode in args.modes}
    processes, urls = {}, {}
    try:
        for mode, (batch_size, model_calls) in settings.items():
            port = free_port()
            urls[mode] = f"http://127.0.0.1:{port}"
            processes[mode] = start_service(batch_size, port, model_calls)
        for mode, url in urls.items():
            wait_ready(url, processes[mode])
            asyncio.run(loadgen.closed_loop(url, bodies, 4, 3.0))  # connections and first calls, unmeasured
        served = loadgen.served_model(urls[args.modes[0]])

        # Every (mode, clients) window once per round, the order rotated from round to round.
        slots = [(mode, clients) for mode in args.modes for clients in CLIENT_COUNTS]
        rounds = []
        for index in range(args.rounds):
            shift = index % len(slots)
            measured = {}
            for mode, clients in slots[shift:] + slots[:shift]:
                measured[f"{mode}/{clients}"] = window(urls[mode], bodies, clients, args.window)
            rounds.append(measured)
            print(
                f"round {index + 1}: "
                + ", ".join(
                    f"{mode} {measured[f'{mode}/16']['pairs_per_s']:.2f} / {measured[f'{mode}/1']['pairs_per_s']:.2f} "
                    f"pairs/s at 16 / 1 clients"
                    for mode in args.modes
                ),
                flush=True,
            )
    finally:
        for process in processes.values():  # one at a time: the second waits while the first drains
            stop_service(process)

    summary = {}
    for mode in args.modes:
        ratios = [r[f"{mode}/16"]["pairs_per_s"] / r[f"{mode}/1"]["pairs_per_s"] for r in rounds]
        summary[mode] = {
            "max_batch_size": settings[mode][0],
            "model_calls": settings[mode][1],
            "median_ratio": statistics.median(ratios),
            "ratios": ratios,
            "median_pairs_per_s": {
                str(clients): statistics.median(r[f"{mode}/{clients}"]["pairs_per_s"] for r in rounds)
                for clients in CLIENT_COUNTS
            },
            "median_p50_ms_1_client": statistics.median(r[f"{mode}/1"]["p50_ms"] for r in rounds),
        }
        print(
            f"{mode}: median ratio 16 / 1 clients {summary[mode]['median_ratio']:.2f}x "
            f"(range {min(ratios):.2f}-{max(ratios):.2f}x)"
        )

    record = {
        **run_header(),
        "model": served,
        "window_s": args.window,
        "rounds": rounds,
        "modes": summary,
    }
    write_record(args.out, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
