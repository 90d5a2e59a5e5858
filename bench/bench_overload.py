"""Overload benchmark: twice the measured capacity for 60 s, then SIGTERM under load.

1. Capacity: a `python -m service` process (the shipped settings: batching, queue, timeout) on a
   free loopback port; `--capacity-clients` closed-loop clients for `--capacity-duration` s give
   the pairs/s it sustains (or pass `--capacity`).
2. Overload: Poisson arrivals at `--factor` x capacity for `--duration` s (open loop: arrivals do
   not wait for answers), model-sized JSON pairs. Every request is followed to its answer.
   Checked: only 200 and the declared 429 (busy or queue full) / 503 (stopping) answers, no transport
   errors or client timeouts (no request lost), p99 of accepted requests below the request
   timeout, resident memory flat, `/ready` 200 and the queue empty again right after.
3. SIGTERM under load: closed-loop clients keep sending; SIGTERM arrives mid-run. Every request
   that was in flight when it arrived must get its answer (200, or 503 if it had not reached the
   model), the process must exit by itself, within the grace period.

    python bench/bench_overload.py                     # ~2.5 minutes
    python bench/bench_overload.py --capacity 9.5 --duration 30

Writes docs/benchmarks/overload.json (read by bench/report.py). Loopback only; the service
process is always stopped.
"""

import argparse
import asyncio
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import loadgen  # noqa: E402
from bench_batching import free_port, service_command, stop_service, wait_ready  # noqa: E402
from records import run_header, write_record  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.settings import Settings  # noqa: E402

DECLARED = {"200", "429", "503"}


def start(port: int, log: Path, **settings: str) -> subprocess.Popen:
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "IFNET_LOG_LEVEL": "info",
        **{f"IFNET_{key.upper()}": value for key, value in settings.items()},
    }
    with log.open("w") as output:
        return subprocess.Popen(service_command(port), env=env, stdout=output, stderr=subprocess.STDOUT)


def rss_trend(samples: list[tuple[float, float]], skip_s: float) -> dict:
    """Growth of resident memory after the first `skip_s` seconds: slope and first/last values."""
    steady = [(t, mb) for t, mb in samples if t >= skip_s]
    if len(steady) < 3:
        return {}
    times, mbs = np.array(steady).T
    slope = float(np.polyfit(times, mbs, 1)[0]) * 60.0
    return {
        "after_warmup_mb": float(mbs[0]),
        "end_mb": float(mbs[-1]),
        "max_mb": float(mbs.max()),
        "slope_mb_per_min": slope,
    }


class Prober:
    """Polls GET `path` once a second on a thread of its own, like a readiness probe would."""

    def __init__(self, url: str, path: str = "/ready", timeout_s: float = 5.0):
        self.url, self.path, self.timeout_s = url, path, timeout_s
        self.samples: list[dict] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._started = time.perf_counter()

    def __enter__(self) -> "Prober":
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=self.timeout_s, trust_env=False) as client:
            while not self._stop.is_set():
                sent = time.perf_counter()
                try:
                    status = client.get(self.path).status_code
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                self.samples.append(
                    {"t": round(sent - self._started, 2), "status": status, "ms": 1000 * (time.perf_counter() - sent)}
                )
                self._stop.wait(max(0.0, 1.0 - (time.perf_counter() - sent)))


def overload_phase(url: str, pid: int, bodies, rate: float, duration: float, timeout_s: float) -> dict:
    before = loadgen.metric_values(url)
    with loadgen.RssSampler(pid, interval_s=0.5) as rss, Prober(url) as probe:
        run = asyncio.run(loadgen.open_loop(url, bodies, rate, duration, timeout_s))
    after = loadgen.metric_values(url)
    drained_at = time.perf_counter()
    health = httpx.get(f"{url}/health", timeout=10, trust_env=False).json()
    ready_wait = None
    for _ in range(600):
        if httpx.get(f"{url}/ready", timeout=10, trust_env=False).status_code == 200:
            ready_wait = time.perf_counter() - drained_at
            break
        time.sleep(0.05)
    summary = run.summary()
    probe_ms = np.array([sample["ms"] for sample in probe.samples])
    per_second = Counter()
    for outcome in run.outcomes:
        per_second[(int(outcome.sent_at), str(outcome.status) if outcome.status else "error")] += 1
    accepted = np.array([o.latency_s for o in run.outcomes if o.status == 200])
    rejected = np.array([o.latency_s for o in run.outcomes if o.status == 429])
    return {
        **summary,
        "offered_per_s": summary["requests"] / duration,
        "rate_per_s": rate,
        "undeclared": {k: v for k, v in summary["statuses"].items() if k not in DECLARED},
        "accepted_p99_ms": float(np.percentile(accepted, 99) * 1000) if len(accepted) else None,
        "rejected_p99_ms": float(np.percentile(rejected, 99) * 1000) if len(rejected) else None,
        "rejections": {
            key.split("reason=")[1].rstrip("}"): after[key] - before.get(key, 0.0)
            for key in after
            if key.startswith("ifnet_batcher_rejections_total{")
        },
        "batching": loadgen.batching_stats(before, after),
        "health_after": health,
        "ready_after_s": ready_wait,
        "ready_probe_during": {
            "count": len(probe.samples),
            "statuses": dict(Counter(str(sample["status"]) for sample in probe.samples)),
            "p50_ms": float(np.percentile(probe_ms, 50)) if len(probe_ms) else None,
            "max_ms": float(probe_ms.max()) if len(probe_ms) else None,
        },
        "ready_probe_samples": probe.samples,
        "rss": rss_trend(rss.samples, skip_s=10.0),
        "rss_samples": [(round(t, 2), round(mb, 1)) for t, mb in rss.samples],
        "per_second": [
            {"t": second, "status": status, "count": count} for (second, status), count in sorted(per_second.items())
        ],
    }


async def sigterm_phase(url: str, process: subprocess.Popen, bodies, clients: int, before_s: float) -> dict:
    """Closed-loop load; SIGTERM after `before_s`; every outcome kept with whether it was in flight."""
    outcomes: list[dict] = []
    signalled_at: list[float] = []
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=120, trust_env=False) as client:
        started = time.perf_counter()

        async def worker(index: int) -> None:
            turn = index
            while process.poll() is None and time.perf_counter() - started < before_s + 60:
                body = bodies[turn % len(bodies)]
                turn += clients
                sent = time.perf_counter()
                try:
                    response = await client.post("/register", content=body.content, headers=body.headers)
                    status, error = response.status_code, ""
                except httpx.HTTPError as exc:
                    status, error = 0, type(exc).__name__
                in_flight = bool(signalled_at) and sent < signalled_at[0]
                outcomes.append(
                    {
                        "status": status,
                        "error": error,
                        "in_flight_at_sigterm": in_flight,
                        "sent_after_sigterm": bool(signalled_at) and not in_flight,
                    }
                )
                if status == 0 and signalled_at:
                    return  # the listener is closed: this client is done

        async def terminate() -> None:
            await asyncio.sleep(before_s)
            signalled_at.append(time.perf_counter())
            process.send_signal(signal.SIGTERM)

        await asyncio.gather(terminate(), *(worker(i) for i in range(clients)))
    exit_code = await asyncio.to_thread(process.wait, 120)
    exited_after = time.perf_counter() - signalled_at[0]

    def count(rows) -> dict:
        return dict(sorted(Counter(str(r["status"]) if r["status"] else f"error:{r['error']}" for r in rows).items()))

    in_flight = [r for r in outcomes if r["in_flight_at_sigterm"]]
    return {
        "clients": clients,
        "sigterm_after_s": before_s,
        "in_flight_at_sigterm": len(in_flight),
        "in_flight_outcomes": count(in_flight),
        "before_sigterm_outcomes": count(
            [r for r in outcomes if not r["in_flight_at_sigterm"] and not r["sent_after_sigterm"]]
        ),
        "sent_after_sigterm_outcomes": count([r for r in outcomes if r["sent_after_sigterm"]]),
        "exit_code": exit_code,
        "exited_after_s": exited_after,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capacity", type=float, help="pairs/s the service sustains (default: measure it)")
    parser.add_argument("--capacity-clients", type=int, default=16)
    parser.add_argument("--capacity-duration", type=float, default=15.0)
    parser.add_argument("--factor", type=float, default=2.0, help="offered load as a multiple of capacity")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of overload")
    parser.add_argument("--sigterm-clients", type=int, default=16)
    parser.add_argument("--sigterm-after", type=float, default=5.0)
    parser.add_argument("--payload", choices=["model", "scan"], default="model", help="768-point or real-scan pairs")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "overload.json")
    args = parser.parse_args()
    if not 0 < args.duration <= 300 or not 0 < args.factor <= 10 or not 0 < args.capacity_duration <= 60:
        parser.error("--duration must be in (0, 300], --factor in (0, 10], --capacity-duration in (0, 60]")
    if not loadgen.scans_available():
        print(f"real scans not found at {loadgen.REAL_SCANS}", file=sys.stderr)
        return 2
    bodies = loadgen.model_sized_bodies(768) if args.payload == "model" else loadgen.scan_bodies("json")
    log = Path(tempfile.mkdtemp(prefix="ifnet-overload-")) / "service.log"
    record: dict = {
        **run_header(),
        "machine": {"cpus": os.cpu_count()},
        "request_timeout_s": Settings().request_timeout_s,  # the service's, from the same environment
        # What the service reads from the same environment: its defaults unless IFNET_* are set.
        "settings": Settings().model_dump(
            include={"max_batch_size", "model_calls", "max_queue_size", "max_in_flight", "shutdown_timeout_s"}
        ),
        "payload": args.payload,
        "payload_points": sorted({body.points for body in bodies}),
    }

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    process = start(port, log)
    try:
        wait_ready(url, process)
        record["model"] = loadgen.served_model(url)
        record["rss_ready_mb"] = loadgen.proc_status_kb(process.pid, "VmRSS") / 1024
        capacity = args.capacity
        if capacity is None:
            asyncio.run(loadgen.closed_loop(url, bodies, args.capacity_clients, 3.0))
            run = asyncio.run(loadgen.closed_loop(url, bodies, args.capacity_clients, args.capacity_duration))
            capacity = run.summary()["pairs_per_s"]
            record["capacity_run"] = run.summary() | {"clients": args.capacity_clients}
        record["capacity_pairs_per_s"] = capacity
        rate = args.factor * capacity
        print(f"capacity {capacity:.2f} pairs/s; offering {rate:.2f} requests/s for {args.duration:.0f} s", flush=True)
        overload = overload_phase(
            url, process.pid, bodies, rate, args.duration, timeout_s=record["request_timeout_s"] + 30
        )
        record["overload"] = overload
        shown = ("requests", "statuses", "p50_ms", "accepted_p99_ms", "rejected_p99_ms", "rss", "ready_after_s")
        print("overload:", {key: overload[key] for key in shown}, flush=True)
        print("  /ready during:", overload["ready_probe_during"], "health after:", overload["health_after"], flush=True)
        sigterm = asyncio.run(sigterm_phase(url, process, bodies, args.sigterm_clients, args.sigterm_after))
        record["sigterm"] = sigterm
        print(f"sigterm: {sigterm}", flush=True)
    finally:
        stop_service(process)
    text = log.read_text()
    record["log_checks"] = {
        "tracebacks": text.count("Traceback"),
        "batcher_drained": "batcher drained" in text,
        "finished": "Finished server process" in text,
    }
    record["verdict"] = verdict(record)
    print(f"verdict: {record['verdict']}")
    write_record(args.out, record)
    print(f"server log: {log}")
    return 0


def verdict(record: dict) -> dict[str, bool]:
    overload, sigterm = record["overload"], record["sigterm"]
    rss = overload["rss"]
    return {
        "only_declared_statuses": not overload["undeclared"],
        "no_request_lost": not any(key.startswith("error") for key in overload["statuses"]),
        "accepted_p99_below_timeout": overload["statuses"].get("200", 0) > 0  # no p99 without accepted requests
        and overload["accepted_p99_ms"] < 1000 * record["request_timeout_s"],
        "memory_flat": bool(rss) and rss["end_mb"] - rss["after_warmup_mb"] < 50 and rss["slope_mb_per_min"] < 20,
        "ready_recovers": overload["ready_after_s"] is not None
        and overload["health_after"]["queue_depth"] == 0
        and overload["health_after"]["in_flight"] == 0,
        "sigterm_in_flight_answered": sigterm["in_flight_at_sigterm"] > 0
        and set(sigterm["in_flight_outcomes"]) <= {"200", "503"},
        "sigterm_exits_cleanly": sigterm["exit_code"] in (0, -signal.SIGTERM)
        and sigterm["exited_after_s"] <= record["settings"]["shutdown_timeout_s"]
        and record["log_checks"]["batcher_drained"]
        and record["log_checks"]["tracebacks"] == 0,
    }


if __name__ == "__main__":
    sys.exit(main())
