"""Which of two or more ONNX files of the model is faster, on a machine whose speed drifts.

Timings taken minutes apart on this shared 2-CPU machine can differ 2x (bench/machine_check.py),
so comparing two exports by separate runs says little. This runs one call of each model in turn,
round after round, on the same clouds (batch 1, the first model's point count, `--threads`
threads), so drift reaches every model alike, and prints each model's median and its ratio to
the first. To time the committed model against an earlier export:

    git show <commit>:service/models/ifnet.onnx > /tmp/earlier.onnx
    python bench/compare_models.py /tmp/earlier.onnx service/models/ifnet.onnx
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from machine_check import example_feeds, session


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path, nargs="+", help="two or more .onnx files")
    parser.add_argument("--rounds", type=int, default=40)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    if len(args.models) < 2:
        parser.error("give at least two models to compare")

    sessions = [session(model, args.threads) for model in args.models]
    feeds = example_feeds(sessions[0])
    for s in sessions:  # warm-up
        s.run(None, feeds)
    ms = np.zeros((args.rounds, len(sessions)))
    for r in range(args.rounds):
        for i in np.roll(np.arange(len(sessions)), r):  # rotate who goes first
            started = time.perf_counter()
            sessions[i].run(None, feeds)
            ms[r, i] = 1000 * (time.perf_counter() - started)
    medians = np.median(ms, axis=0)
    for model, median in zip(args.models, medians, strict=True):
        print(f"{median:8.1f} ms  ({median / medians[0]:.2f}x the first)  {model}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
