"""Where `auto`'s time goes, pair by pair, in one process: each step of the pipeline (every CPU-heavy
function that register_clouds runs through its `run_blocking` hook) and each network's calls, beside
the classical peers on the same pairs.

    python -m bench.stages --sets same:clean same:jitter:so3:50 indoor --peers

Per set: for each step and each network's calls, the pairs that ran it, its median per pair where it
ran, its total and its share of `auto`'s total; the stages that gave the answers; `auto`'s median time
per pair and, with --peers, the median per-pair ratio to Open3D FPFH + RANSAC + ICP and to
KISS-Matcher + GICP, interleaved pair by pair. Sets as bench.harness.pair_set names them.

The steps run one after another (bench.ab's networks and `in_turn`): the draft's first call follows
feature matching, where the service runs it beside feature matching's child process. On 2 CPUs the
two then slow each other about as much as running them in turn costs, so the ratios to the peers
come out near the service's over HTTP (docs/benchmarks.md); the steps' own times do not.
"""

import argparse
import asyncio
import dataclasses
import statistics
import time
from collections import Counter, defaultdict
from pathlib import Path

from bench import ab, harness
from service.registration import Network, register_clouds
from service.schemas import RefineOptions, RegistrationOptions
from service.settings import Settings

PEERS = {"open3d": harness.open3d_fpfh_ransac_icp, "kiss": harness.kiss_matcher_gicp}


class StageClock:
    """Milliseconds per step and per network call of the request being timed."""

    def __init__(self):
        self.spent: defaultdict[str, float] = defaultdict(float)

    async def run_blocking(self, function, *args, **kwargs):
        started = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            self.spent[function.__name__] += (time.perf_counter() - started) * 1000.0

    def timed(self, network: Network) -> Network:
        """The network, its calls (and its draft's) counted under "<model> <stage> call"."""
        key = f"{network.model} {network.stage} call"

        async def predict(source, target):
            started = time.perf_counter()
            try:
                return await network.predict(source, target)
            finally:
                self.spent[key] += (time.perf_counter() - started) * 1000.0

        draft = None if network.draft is None else self.timed(network.draft)
        return dataclasses.replace(network, predict=predict, draft=draft)


def run(args: argparse.Namespace) -> dict:
    settings = Settings()
    clock = StageClock()
    nets = [clock.timed(network) for network in ab.networks(settings)]
    options = RegistrationOptions(method="auto", refine=RefineOptions())
    order = ["auto", *PEERS] if args.peers else ["auto"]

    def timed(method: str, pair: harness.Pair, row: dict) -> None:
        started = time.perf_counter()
        if method == "auto":
            result = asyncio.run(
                register_clouds(pair.source, pair.target, options, settings, nets, clock.run_blocking, settings.threads)
            )
            row["stage"] = result.stage
        else:
            PEERS[method](pair.source, pair.target, pair.voxel)
        row[method] = (time.perf_counter() - started) * 1000.0

    record = harness.run_header() | {"sets": {}}
    for spec in args.sets:
        pairs = harness.pair_set(spec)
        for method in order:  # sessions, imports and caches warm before anything is timed
            timed(method, pairs[0], {})
        rows = []
        for index, pair in enumerate(pairs):
            clock.spent.clear()
            row = {"pair": pair.name}
            for method in order[index % len(order) :] + order[: index % len(order)]:
                timed(method, pair, row)
            row["steps"] = dict(clock.spent)
            rows.append(row)
        record["sets"][spec] = summarise(rows, args.peers)
        report(spec, record["sets"][spec])
    return record


def summarise(rows: list[dict], peers: bool) -> dict:
    total = sum(row["auto"] for row in rows)
    steps = {}
    for name in sorted({name for row in rows for name in row["steps"]}):
        spent = [row["steps"][name] for row in rows if name in row["steps"]]
        steps[name] = {
            "pairs": len(spent),
            "median_ms": statistics.median(spent),
            "total_ms": sum(spent),
            "share": sum(spent) / total,
        }
    summary = {
        "pairs": len(rows),
        "median_ms": statistics.median(row["auto"] for row in rows),
        "total_ms": total,
        "answers": dict(Counter(row["stage"] for row in rows)),
        "steps": steps,
        "rows": rows,
    }
    if peers:
        summary["ratio_to"] = {peer: statistics.median(row["auto"] / row[peer] for row in rows) for peer in PEERS}
    return summary


def report(spec: str, summary: dict) -> None:
    print(f"{spec}: {summary['pairs']} pairs, auto median {summary['median_ms']:.1f} ms, answers {summary['answers']}")
    if "ratio_to" in summary:
        print("  auto / peer, median per pair: " + ", ".join(f"{p} {r:.2f}x" for p, r in summary["ratio_to"].items()))
    for name, numbers in sorted(summary["steps"].items(), key=lambda item: -item[1]["total_ms"]):
        print(
            f"  {name:28s} pairs {numbers['pairs']:4d}  median {numbers['median_ms']:7.1f} ms  "
            f"total {numbers['total_ms'] / 1000:6.2f} s  {numbers['share']:6.1%}"
        )


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--sets", nargs="+", required=True, help="split:noise[:so3][:count], indoor, outdoor[:shared], truth, scans"
    )
    p.add_argument("--peers", action="store_true", help="also time Open3D and KISS-Matcher + GICP on each pair")
    p.add_argument("--out", type=Path, help="write the record (every pair's steps) here as JSON")
    args = p.parse_args(argv)
    record = run(args)
    if args.out:
        harness.write_record(args.out, record)


if __name__ == "__main__":
    main()
