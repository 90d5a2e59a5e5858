"""Service benchmark: /register throughput and latency by concurrency, batching and payload size.

For each mode (off: IFNET_MAX_BATCH_SIZE=1 and IFNET_MODEL_CALLS=2, the shipped defaults, under
which a call that starts alone runs on both ONNX Runtime threads and two calls side by side on one
each; on: the same with batches of up to --batch-size; 1call: batch 1, one call at a time on both
threads) one `python -m service` process is started on a free loopback port
(bench_batching.start_service) and awaited. Each payload first gets `--warmup` seconds of
unmeasured load from 4 clients; then, per client count, a closed loop of asyncio clients (httpx)
posts pre-encoded requests for `--duration` seconds.
Reported per cell: pairs/s, latency p50/p95/p99 of successful requests, status counts, mean
batch size, queue wait and model-call time (from /metrics deltas), the server's CPU use and
peak resident memory.

Payloads: `model` = 768 points per cloud (the network's own size, random subsets of real
scans); `scan` = real scans (12k-100k points per cloud) as JSON; `scan-npz` = the same scans as
a raw NPZ body. Client counts: 1, 4, 16, 64 (`scan-npz`: 1 and 16). A closed loop stops sending
after `--duration` but waits for the answers in flight, which are counted (the time too).

    python bench/bench_service.py                               # the full matrix, ~12 minutes
    python bench/bench_service.py --clients 1 16 --payloads model --duration 5

Writes docs/benchmarks/service.json (read by bench/report.py). Everything stays on 127.0.0.1
and each process is stopped with SIGTERM.
"""

import argparse
import asyncio
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import loadgen  # noqa: E402
from bench_batching import free_port, start_service, stop_service, wait_ready  # noqa: E402
from records import run_header, write_record  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# mode -> (max batch size, or None for --batch-size; model calls at once). `off` is the shipped
# default (service/settings.py); `1call` runs one call at a time on every thread, whatever the load.
MODES = {"off": (1, 2), "on": (None, 2), "1call": (1, 1)}
BATCH_SIZE_ON = 4  # --batch-size's default
DEFAULT_CLIENTS = {"model": [1, 4, 16, 64], "scan": [1, 4, 16, 64], "scan-npz": [1, 16]}
PAYLOADS = {
    "model": lambda: loadgen.model_sized_bodies(768),
    "scan": lambda: loadgen.scan_bodies("json"),
    "scan-npz": lambda: loadgen.scan_bodies("npz"),
}


def measure_cell(url: str, pid: int, bodies, clients: int, duration: float) -> dict:
    before = loadgen.metric_values(url)
    cpu_before = loadgen.cpu_seconds(pid)
    own_before = time.process_time()
    with loadgen.RssSampler(pid) as rss:
        run = asyncio.run(loadgen.closed_loop(url, bodies, clients, duration))
    cell = run.summary()
    cell |= loadgen.batching_stats(before, loadgen.metric_values(url))
    cell["server_cpus"] = (loadgen.cpu_seconds(pid) - cpu_before) / run.seconds
    cell["loadgen_cpus"] = (time.process_time() - own_before) / run.seconds
    cell["server_rss_mb_peak_during"] = rss.peak_mb
    cell["server_vmhwm_mb"] = loadgen.proc_status_kb(pid, "VmHWM") / 1024
    return cell


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, nargs="+", help="client counts (default: per payload, see above)")
    parser.add_argument("--payloads", nargs="+", default=list(PAYLOADS), choices=list(PAYLOADS))
    parser.add_argument("--batch-size", type=int, default=BATCH_SIZE_ON, help="IFNET_MAX_BATCH_SIZE with batching on")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--duration", type=float, default=12.0, help="measured seconds per cell")
    parser.add_argument("--warmup", type=float, default=3.0, help="unmeasured seconds per payload")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "service.json")
    args = parser.parse_args()
    if not 0 < args.duration <= 120 or not 0 <= args.warmup <= 30 or not all(1 <= c <= 256 for c in args.clients or []):
        parser.error("--duration must be in (0, 120], --warmup in [0, 30], --clients in [1, 256]")
    if not loadgen.scans_available():
        print(f"real scans not found at {loadgen.REAL_SCANS}", file=sys.stderr)
        return 2

    bodies = {name: PAYLOADS[name]() for name in args.payloads}
    for name, items in bodies.items():
        sizes = sorted({body.points for body in items})
        print(
            f"payload {name}: {len(items)} bodies, {sizes} points per cloud, "
            f"{sum(len(b.content) for b in items) / len(items) / 1e6:.2f} MB each on average",
            flush=True,
        )

    cells = []
    print("mode    payload   clients  pairs/s   p50 ms   p95 ms   p99 ms  batch  queue ms  srv CPUs  RSS MB  statuses")
    for mode in args.modes:
        batch_size, model_calls = MODES[mode]
        batch_size = batch_size or args.batch_size
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        process = start_service(batch_size, port, model_calls)
        try:
            wait_ready(url, process)
            served = loadgen.served_model(url)
            for payload, items in bodies.items():
                # Warm-up once per payload (connections, first calls at each size); later cells follow on.
                asyncio.run(loadgen.closed_loop(url, items, 4, args.warmup))
                for clients in args.clients if args.clients else DEFAULT_CLIENTS[payload]:
                    cell = measure_cell(url, process.pid, items, clients, args.duration)
                    cell |= {"mode": mode, "max_batch_size": batch_size, "model_calls": model_calls}
                    cell |= {"payload": payload, "clients": clients}
                    cell["points_per_cloud"] = sorted({body.points for body in items})
                    cells.append(cell)
                    print(
                        f"{mode:6s}  {payload:8s}  {clients:7d}  {cell['pairs_per_s']:7.2f}  "
                        f"{fmt(cell['p50_ms'])}  {fmt(cell['p95_ms'])}  {fmt(cell['p99_ms'])}  "
                        f"{cell['mean_batch']:5.2f}  {cell['mean_queue_ms']:8.0f}  {cell['server_cpus']:8.2f}  "
                        f"{cell['server_vmhwm_mb']:6.0f}  {cell['statuses']}",
                        flush=True,
                    )
        finally:
            stop_service(process)

    record = {
        **run_header(),
        "machine": {"cpus": os.cpu_count(), "arch": platform.machine(), "loadavg_at_end": os.getloadavg()},
        "model": served,
        "duration_s": args.duration,
        "warmup_s": args.warmup,
        "cells": cells,
    }
    write_record(args.out, record)
    return 0


def fmt(value: float | None) -> str:
    return "      -" if value is None else f"{value:7.0f}"


if __name__ == "__main__":
    sys.exit(main())
