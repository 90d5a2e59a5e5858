"""Model throughput: one 2-thread call at a time against two 1-thread calls at once.

The service gives a model call that starts alone every thread and calls side by side a share each
(`IFNET_MODEL_CALLS`, default 2). This times both ways on the served model (batch 1, its native
point count, no HTTP) in alternating windows of `--window` seconds, so that the machine's drifting
speed reaches both alike, and prints pairs/s per window pair and the median ratio. The service's
own figures (HTTP, parsing, the load generator on the same CPUs) are in bench/bench_service.py
and bench/bench_scaling.py.

    python bench/bench_calls.py
    python bench/bench_calls.py --windows 4 --window 3

Writes docs/benchmarks/calls.json (read by bench/report.py).
"""

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
from machine_check import DEFAULT_MODEL, ROOT, timed_model, warm_sessions
from records import run_header, write_record


def pairs_per_second(model: ort.InferenceSession, feeds: dict, calls_at_once: int, seconds: float) -> float:
    """Completed calls per second of `calls_at_once` threads each calling back to back for `seconds`."""
    completed = [0] * calls_at_once
    deadline = time.perf_counter() + seconds

    def call_until_deadline(slot: int) -> None:
        while time.perf_counter() < deadline:
            model.run(None, feeds)
            completed[slot] += 1

    started = time.perf_counter()
    threads = [threading.Thread(target=call_until_deadline, args=(slot,)) for slot in range(calls_at_once)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return sum(completed) / (time.perf_counter() - started)  # the last calls finish after the deadline


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    parser.add_argument("--windows", type=int, default=8, help="window pairs (one of each way)")
    parser.add_argument("--window", type=float, default=5.0, help="seconds per window")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "calls.json")
    args = parser.parse_args()
    if not 1 <= args.windows <= 50 or not 1 <= args.window <= 60:
        parser.error("--windows must be in [1, 50] and --window in [1, 60]")

    # As in the service, the two concurrent callers share one (1-thread) session.
    one_call, two_calls, feeds = warm_sessions(args.model)
    windows = []
    for index in range(args.windows):
        order = [(one_call, 1), (two_calls, 2)] if index % 2 == 0 else [(two_calls, 2), (one_call, 1)]
        rates = {calls: pairs_per_second(model, feeds, calls, args.window) for model, calls in order}
        windows.append({"one_2_thread_call": rates[1], "two_1_thread_calls": rates[2]})
        print(
            f"window {index + 1}: one 2-thread call at a time {rates[1]:5.2f} pairs/s, "
            f"two 1-thread calls at once {rates[2]:5.2f} pairs/s ({rates[2] / rates[1]:.2f}x)",
            flush=True,
        )
    ratios = [w["two_1_thread_calls"] / w["one_2_thread_call"] for w in windows]
    print(f"median ratio {np.median(ratios):.2f}x (range {min(ratios):.2f}-{max(ratios):.2f}x)")

    record = {
        **run_header(),
        "model": timed_model(one_call, args.model),
        "window_s": args.window,
        "windows": windows,
        "median_ratio": float(np.median(ratios)),
    }
    write_record(args.out, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
