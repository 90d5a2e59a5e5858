"""Load-generation pieces shared by bench_service.py and bench_overload.py.

The service process itself is started and awaited with bench_batching's helpers; this module
adds what a longer measurement needs: request bodies of two sizes, a closed-loop and an
open-loop driver that keep every outcome (status or transport error, latency, when), the
server's memory and CPU from /proc, and counter deltas from /metrics.
"""

import asyncio
import io
import json
import os
import random
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_batching import REAL_SCANS, request_body  # noqa: E402

# Real scans whose halves (70 % of the points each, see bench_batching.request_body) give
# 12k-35k points per cloud, plus an office scan whose halves are cut to 100k points each: the
# real-scan-sized payloads, 10k-100k points.
SCAN_SIZED = ("kitti_000008_fov", "nuscenes_lidar_top", "scannet_scene0000_00", "sunrgbd_000017")
LARGE_SCAN = "pcl_office1"
LARGE_POINTS = 100_000
JSON_HEADERS = {"content-type": "application/json"}


@dataclass(frozen=True)
class Body:
    content: bytes
    headers: dict[str, str]
    points: int  # per cloud (the larger of the two)


def scan_bodies(encoding: str = "json", seed: int = 0) -> list[Body]:
    """One pair per real scan (a rigid motion of two overlapping 70 % halves), 12k-100k points per cloud."""
    bodies = []
    rng = np.random.default_rng(seed)
    for index, scan in enumerate((*SCAN_SIZED, LARGE_SCAN)):
        pair = json.loads(request_body(scan, seed + index))
        for name in ("source", "target"):
            if len(pair[name]) > LARGE_POINTS:
                pair[name] = [pair[name][i] for i in np.sort(rng.choice(len(pair[name]), LARGE_POINTS, replace=False))]
        points = max(len(pair["source"]), len(pair["target"]))
        if encoding == "json":
            bodies.append(Body(json.dumps(pair).encode(), JSON_HEADERS, points))
        else:
            stream = io.BytesIO()
            np.savez(stream, source=np.asarray(pair["source"]), target=np.asarray(pair["target"]))
            bodies.append(Body(stream.getvalue(), {"content-type": "application/x-npz"}, points))
    return bodies


def model_sized_bodies(points: int = 768, count: int = 8, seed: int = 0) -> list[Body]:
    """Pairs of `points` points per cloud (the network's own size): random subsets of real scan pairs."""
    rng = np.random.default_rng(seed)
    bodies = []
    for index in range(count):
        pair = json.loads(request_body(SCAN_SIZED[index % len(SCAN_SIZED)], seed + index))
        small = {
            name: np.asarray(pair[name])[np.sort(rng.choice(len(pair[name]), points, replace=False))].tolist()
            for name in ("source", "target")
        }
        bodies.append(Body(json.dumps(small).encode(), JSON_HEADERS, points))
    return bodies


# ---------------------------------------------------------------- outcomes


@dataclass
class Outcome:
    sent_at: float  # seconds since the run started
    latency_s: float
    status: int  # 0 for a transport error
    error: str = ""  # exception type for transport errors
    retry_after_s: float = 0.0  # the Retry-After header of a 429 or 503


@dataclass
class Run:
    outcomes: list[Outcome] = field(default_factory=list)
    seconds: float = 0.0

    def summary(self) -> dict:
        ok = np.array([o.latency_s for o in self.outcomes if o.status == 200]) * 1000.0
        statuses = Counter(str(o.status) if o.status else f"error:{o.error}" for o in self.outcomes)
        p50, p95, p99 = np.percentile(ok, [50, 95, 99]).tolist() if len(ok) else (None, None, None)
        return {
            "seconds": round(self.seconds, 3),
            "requests": len(self.outcomes),
            "ok": int(len(ok)),
            "pairs_per_s": len(ok) / self.seconds if self.seconds else 0.0,
            "p50_ms": p50,
            "p95_ms": p95,
            "p99_ms": p99,
            "max_ms": float(ok.max()) if len(ok) else None,
            "statuses": dict(sorted(statuses.items())),
        }


async def _send(client: httpx.AsyncClient, body: Body, started: float, path: str) -> Outcome:
    sent = time.perf_counter()
    try:
        response = await client.post(path, content=body.content, headers=body.headers)
        status, error = response.status_code, ""
        retry_after = float(response.headers.get("retry-after", 0))
    except httpx.HTTPError as exc:
        status, error, retry_after = 0, type(exc).__name__, 0.0
    return Outcome(sent - started, time.perf_counter() - sent, status, error, retry_after)


async def closed_loop(
    url: str, bodies: list[Body], clients: int, duration_s: float, timeout_s: float = 120.0, path: str = "/register"
) -> Run:
    """`clients` clients, each sending its next request as soon as the last one is answered, or
    after the Retry-After seconds of a refusal (as a well-behaved client would)."""
    run = Run()
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=timeout_s, trust_env=False) as client:
        started = time.perf_counter()
        deadline = started + duration_s

        async def worker(index: int) -> None:
            turn = index
            while time.perf_counter() < deadline:
                outcome = await _send(client, bodies[turn % len(bodies)], started, path)
                run.outcomes.append(outcome)
                turn += clients
                if outcome.retry_after_s:
                    await asyncio.sleep(min(outcome.retry_after_s, max(0.0, deadline - time.perf_counter())))

        await asyncio.gather(*(worker(i) for i in range(clients)))
        run.seconds = time.perf_counter() - started
    return run


async def open_loop(
    url: str,
    bodies: list[Body],
    rate_per_s: float,
    duration_s: float,
    timeout_s: float,
    seed: int = 0,
    path: str = "/register",
    on_tick=None,
) -> Run:
    """Poisson arrivals at `rate_per_s` for `duration_s`, whatever the answers; then waits for every answer.

    Each request gets a connection of its own if none is free (the pool is unbounded), so the
    arrival rate does not depend on the server. `on_tick(elapsed)` runs about once a second.
    """
    run = Run()
    rng = random.Random(seed)
    limits = httpx.Limits(max_connections=None, max_keepalive_connections=256)
    pending: set[asyncio.Task] = set()
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=timeout_s, trust_env=False) as client:
        started = time.perf_counter()
        next_arrival, next_tick, index = started, started, 0
        while (now := time.perf_counter()) < started + duration_s:
            if on_tick is not None and now >= next_tick:
                on_tick(now - started)
                next_tick += 1.0
            if now >= next_arrival:
                task = asyncio.ensure_future(_send(client, bodies[index % len(bodies)], started, path))
                task.add_done_callback(lambda done: run.outcomes.append(done.result()))
                pending.add(task)
                task.add_done_callback(pending.discard)
                index += 1
                next_arrival += rng.expovariate(rate_per_s)
                continue
            await asyncio.sleep(min(next_arrival, next_tick) - now if on_tick else next_arrival - now)
        run.seconds = time.perf_counter() - started
        while pending:  # every request must come back (the client timeout bounds this)
            if on_tick is not None:
                on_tick(time.perf_counter() - started)
            await asyncio.wait(set(pending), timeout=1.0)
    return run


# ---------------------------------------------------------------- the server process


def proc_status_kb(pid: int, key: str) -> int:
    """A value of /proc/<pid>/status in kB (VmRSS: resident now, VmHWM: peak resident)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class RssSampler:
    """Samples a process's resident memory every `interval_s` on a thread of its own."""

    def __init__(self, pid: int, interval_s: float = 0.5):
        self.pid = pid
        self.interval_s = interval_s
        self.samples: list[tuple[float, float]] = []  # (seconds, MB)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._started = time.perf_counter()

    def __enter__(self) -> "RssSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                mb = proc_status_kb(self.pid, "VmRSS") / 1024
            except (OSError, KeyError):
                return
            self.samples.append((time.perf_counter() - self._started, mb))
            self._stop.wait(self.interval_s)

    @property
    def peak_mb(self) -> float:
        return max((mb for _, mb in self.samples), default=float("nan"))


def metric_values(url: str) -> dict[str, float]:
    """Every sample of /metrics, keyed by name and sorted labels."""
    values = {}
    text = httpx.get(f"{url}/metrics", timeout=30, trust_env=False).text
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            labels = ",".join(f"{key}={value}" for key, value in sorted(sample.labels.items()))
            values[f"{sample.name}{{{labels}}}"] = sample.value
    return values


def batching_stats(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
    """Mean batch size, queue wait and model-call time between two /metrics snapshots."""

    def delta(name: str) -> float:
        return after.get(name, 0.0) - before.get(name, 0.0)

    calls = delta("ifnet_batch_size_count{}")
    waits = delta("ifnet_queue_wait_seconds_count{}")
    return {
        "model_calls": int(calls),
        "mean_batch": delta("ifnet_batch_size_sum{}") / calls if calls else float("nan"),
        "mean_queue_ms": 1000 * delta("ifnet_queue_wait_seconds_sum{}") / waits if waits else float("nan"),
        "mean_inference_ms": 1000 * delta("ifnet_inference_seconds_sum{}") / calls if calls else float("nan"),
    }


def scans_available() -> bool:
    return REAL_SCANS.is_file()


def served_model(url: str) -> dict:
    """Name, version (weights SHA-256 prefix), preset and file hash of the model a service runs."""
    metadata = httpx.get(f"{url}/v2/models/ifnet", timeout=30, trust_env=False).json()
    parameters = metadata.get("parameters", {})
    return {
        "version": metadata["versions"][0],
        "preset": parameters.get("preset"),
        "native_num_points": parameters.get("native_num_points"),
        "file_sha256": parameters.get("file_sha256"),
    }
