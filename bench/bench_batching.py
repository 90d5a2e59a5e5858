"""Batching benchmark: one service process, /register throughput and latency per max_batch_size.

For each batch size a `python -m service` process is started on a free loopback port
(IFNET_MAX_BATCH_SIZE set, everything else as configured in the environment), /ready is
awaited, and `--requests` registrations of a real scan pair are sent by `--concurrency`
closed-loop asyncio clients. Reported per batch size: pairs per second, latency p50/p95/p99,
mean batch size and mean queue wait (from /metrics), and failures. The process is stopped
with SIGTERM afterwards.

    python bench/bench_batching.py                                  # batch sizes 1 and 4
    python bench/bench_batching.py --batch-sizes 1 2 4 8 --requests 200 --concurrency 16
"""

import argparse
import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

ROOT = Path(__file__).resolve().parents[1]
REAL_SCANS = ROOT.parent / "shared" / "data" / "real_scans.npz"


def request_body(scan: str, seed: int) -> bytes:
    """A pair from a real scan (a random rigid motion of two overlapping halves), JSON-encoded once."""
    rng = np.random.default_rng(seed)
    with np.load(REAL_SCANS) as archive:
        points = archive[scan].astype(np.float64)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0.0, np.pi / 4)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
    order = np.argsort(points[:, 0])
    source = points[order[: int(0.7 * len(points))]]
    target = points[order[int(0.3 * len(points)) :]] @ rotation.T + rng.normal(scale=0.1, size=3)
    return json.dumps({"source": source.tolist(), "target": target.tolist()}).encode()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def service_command(port: int) -> list[str]:
    """`python -m service` on 127.0.0.1:port only, whatever IFNET_HOST says (benchmarks stay on loopback)."""
    return [sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", str(port)]


def start_service(batch_size: int, port: int, model_calls: int | None = None) -> subprocess.Popen:
    """The service on 127.0.0.1:port with this batch size (and model calls; default: the service's)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "IFNET_MAX_BATCH_SIZE": str(batch_size), "IFNET_LOG_LEVEL": "warning"}
    if model_calls is not None:
        env["IFNET_MODEL_CALLS"] = str(model_calls)
    return subprocess.Popen(service_command(port), env=env)


def stop_service(process: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL if it has not exited within 2 minutes: never left running."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=120)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=30)


def wait_ready(url: str, process: subprocess.Popen, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"service exited with {process.returncode}")
        try:
            if httpx.get(f"{url}/ready", timeout=2, trust_env=False).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"{url}/ready not 200 within {timeout:.0f} s")


async def load(url: str, body: bytes, requests: int, concurrency: int) -> tuple[list[float], int, float]:
    latencies: list[float] = []
    failures = 0
    remaining = requests

    async def client_loop(http: httpx.AsyncClient) -> None:
        nonlocal remaining, failures
        while remaining > 0:
            remaining -= 1
            started = time.perf_counter()
            response = await http.post("/register", content=body, headers={"content-type": "application/json"})
            if response.status_code == 200:
                latencies.append(time.perf_counter() - started)
            else:
                failures += 1

    started = time.perf_counter()
    async with httpx.AsyncClient(base_url=url, timeout=300, trust_env=False) as http:
        await asyncio.gather(*(client_loop(http) for _ in range(concurrency)))
    return latencies, failures, time.perf_counter() - started


def server_stats(url: str) -> dict[str, float]:
    values: dict[str, float] = {}
    for family in text_string_to_metric_families(httpx.get(f"{url}/metrics", trust_env=False).text):
        for sample in family.samples:
            if not sample.labels:
                values[sample.name] = sample.value
    return {
        "mean_batch": values["ifnet_batch_size_sum"] / max(values["ifnet_batch_size_count"], 1),
        "mean_queue_ms": 1000
        * values["ifnet_queue_wait_seconds_sum"]
        / max(values["ifnet_queue_wait_seconds_count"], 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--requests", type=int, default=64, help="registrations per batch size")
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--scan", default="pcl_bunny_view0", help="array of ../shared/data/real_scans.npz")
    args = parser.parse_args()

    body = request_body(args.scan, seed=0)
    print(f"scan {args.scan}, {args.requests} requests, concurrency {args.concurrency}")
    print("batch  pairs/s   p50 ms   p95 ms   p99 ms  mean batch  queue ms  failures")
    for batch_size in args.batch_sizes:
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        process = start_service(batch_size, port)
        try:
            wait_ready(url, process)
            asyncio.run(load(url, body, args.concurrency, args.concurrency))  # warm the connection pool
            latencies, failures, seconds = asyncio.run(load(url, body, args.requests, args.concurrency))
            stats = server_stats(url)
        finally:
            stop_service(process)
        p50, p95, p99 = np.percentile(np.asarray(latencies) * 1000, [50, 95, 99]) if latencies else (np.nan,) * 3
        print(
            f"{batch_size:5d}  {len(latencies) / seconds:7.2f}  {p50:7.0f}  {p95:7.0f}  {p99:7.0f}"
            f"  {stats['mean_batch']:10.2f}  {stats['mean_queue_ms']:8.0f}  {failures:8d}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
