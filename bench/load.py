"""Load on a real service process over 127.0.0.1, with 768-point JSON pairs of the paper's protocol.

    python -m bench.load scaling                       # 16 clients vs 1, alternating windows -> scaling.json
    python -m bench.load scaling --setting 1call=model_calls=1 --rounds 4 --window 6
    python -m bench.load overload                      # 2x capacity for 60 s, then SIGTERM -> overload.json
    python -m bench.load soak                          # 4 clients for 10 min, memory per minute -> soak.json
    python -m bench.load --out docs/benchmarks/soak-one-cpu.json soak --setting workers=1 --setting threads=1

scaling: one server per setting runs throughout; windows of 1 and of 16 closed-loop clients
alternate, the order rotating each round, so both counts of a round meet the same machine phase.
overload: capacity from 16 closed-loop clients, then Poisson arrivals at `--factor` x capacity for
`--duration` s, every request followed to its answer while RSS and /ready are sampled; then
closed-loop clients again and SIGTERM in the middle of them.
soak: closed-loop clients for `--duration` s on the ModelNet pairs and the real pairs with ground
truth (20k-27k points each) in turn, RSS sampled each second: does memory settle, or keep growing?
"""

import argparse
import asyncio
import itertools
import json
import random
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

from bench import harness
from service.features import resident_mb

HEADERS = {"content-type": "application/json"}
WIRE_EVENTS = ("connection.connect_tcp.started", "http11.send_request_headers.started")  # httpcore's trace


def bodies(count: int = 8, real: bool = False) -> list[bytes]:
    """`count` ModelNet pairs, and with `real` the real pairs with ground truth after each of them."""
    pairs = harness.modelnet_pairs(count)
    if real:
        pairs = [pair for both in zip(pairs, itertools.cycle(harness.truth_pairs())) for pair in both]
    return [json.dumps({"source": p.source.tolist(), "target": p.target.tolist()}).encode() for p in pairs]


async def send(client: httpx.AsyncClient, body: bytes) -> dict:
    """One request's outcome: its time from the call (`s`) and from when it reached the wire (`wire_s`:
    its connection opening, or its head sent on a kept one); before that it waits in httpx's pool."""
    sent = time.perf_counter()
    wire = []

    async def trace(event: str, _info: dict) -> None:
        if not wire and event in WIRE_EVENTS:
            wire.append(time.perf_counter())

    try:
        response = await client.post("/register", content=body, headers=HEADERS, extensions={"trace": trace})
        status, retry_after = str(response.status_code), float(response.headers.get("retry-after", 0))
    except httpx.HTTPError as error:
        status, retry_after = f"error:{type(error).__name__}: {error}", 0.0
    done = time.perf_counter()
    return {
        "at": sent,
        "s": done - sent,
        "wire_s": done - (wire[0] if wire else sent),
        "status": status,
        "retry_after": retry_after,
    }


async def closed_loop(url: str, payloads: list[bytes], clients: int, seconds: float, stop=None) -> tuple[list, float]:
    """Each client sends its next request when the last is answered (after Retry-After on a refusal);
    once `stop()` is true, a client stops at its first transport error (the listener is closed)."""
    outcomes = []
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=300, trust_env=False) as client:
        started = time.perf_counter()

        async def worker(turn: int) -> None:
            while time.perf_counter() - started < seconds:
                outcome = await send(client, payloads[turn % len(payloads)])
                outcomes.append(outcome)
                turn += clients
                if outcome["status"].startswith("error") and stop and stop():
                    return
                await asyncio.sleep(min(outcome["retry_after"], max(0.0, seconds - (time.perf_counter() - started))))

        await asyncio.gather(*(worker(i) for i in range(clients)))
        return outcomes, time.perf_counter() - started


async def open_loop(
    url: str, payloads: list[bytes], rate: float, seconds: float, timeout_s: float
) -> tuple[list, float]:
    """Poisson arrivals whatever the answers (a connection each if none is free); waits for every answer."""
    rng, tasks = random.Random(0), []
    limits = httpx.Limits(max_connections=None, max_keepalive_connections=256)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=timeout_s, trust_env=False) as client:
        started = next_at = time.perf_counter()
        while time.perf_counter() < started + seconds:
            tasks.append(asyncio.ensure_future(send(client, payloads[len(tasks) % len(payloads)])))
            next_at += rng.expovariate(rate)
            await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
        offered_s = time.perf_counter() - started
        return list(await asyncio.gather(*tasks)), offered_s


def summary(outcomes: list[dict], seconds: float) -> dict:
    ok = [o for o in outcomes if o["status"] == "200"]
    return {
        "requests": len(outcomes),
        "pairs_per_s": len(ok) / seconds,
        "p50_ms": percentile_ms(ok, "s", 50),
        "p99_ms": percentile_ms(ok, "s", 99),
        "statuses": dict(sorted(Counter(o["status"] for o in outcomes).items())),
    }


def percentile_ms(outcomes: list[dict], key: str, q: float) -> float | None:
    return float(np.percentile([o[key] for o in outcomes], q) * 1000) if outcomes else None


def rss_mb(pid: int) -> float:
    """Resident memory of the process and of its descendants (the workers under their supervisor)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    total, pending = 0.0, [pid]
    while pending:
        current = pending.pop()
        pending += children.get(current, [])
        total += resident_mb(current)
    return total


def rss_summary(samples: np.ndarray, slope_from_s: float = 0.0) -> dict[str, float]:
    """(seconds, MB) samples -> the first, last and largest, and the trend (MB per minute, fitted
    from `slope_from_s` on)."""
    trend = samples[samples[:, 0] >= slope_from_s]
    return {
        "first": float(samples[0, 1]),
        "end": float(samples[-1, 1]),
        "max": float(samples[:, 1].max()),
        "slope_per_min": float(np.polyfit(trend[:, 0], trend[:, 1], 1)[0] * 60),
    }


class Sampler:
    """The service's RSS and a /ready probe, about once every `interval_s`, on a thread of its own."""

    def __init__(self, service: harness.Service, interval_s: float = 0.5):
        self.service, self.interval_s = service, interval_s
        self.rss: list[tuple[float, float]] = []
        self.ready: Counter = Counter()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "Sampler":
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        started = time.perf_counter()
        with httpx.Client(base_url=self.service.url, timeout=5, trust_env=False) as client:
            while not self._stop.wait(self.interval_s):
                self.rss.append((time.perf_counter() - started, rss_mb(self.service.pid)))
                try:
                    self.ready[str(client.get("/ready").status_code)] += 1
                except httpx.HTTPError as error:
                    self.ready[type(error).__name__] += 1


def scaling(args) -> int:
    payloads = bodies()
    settings = {"defaults": {}} | harness.parse_settings(args.setting)
    services = {name: harness.Service(**values) for name, values in settings.items()}
    try:
        for service in services.values():
            service.wait_ready()
            asyncio.run(closed_loop(service.url, payloads, 4, 3.0))  # connections and first calls, unmeasured
        slots = [(name, clients) for name in services for clients in (1, 16)]
        rounds = []
        for index in range(args.rounds):
            shift = index % len(slots)
            measured = {}
            for name, clients in slots[shift:] + slots[:shift]:
                outcomes, seconds = asyncio.run(closed_loop(services[name].url, payloads, clients, args.window))
                measured[f"{name}/{clients}"] = summary(outcomes, seconds)
            rounds.append(measured)
            print(
                f"round {index + 1}: " + ", ".join(f"{k} {v['pairs_per_s']:.2f} pairs/s" for k, v in measured.items())
            )
        model = next(iter(services.values())).model()
    finally:
        for service in services.values():
            service.stop()
    result = {}
    for name in settings:
        ratios = [r[f"{name}/16"]["pairs_per_s"] / r[f"{name}/1"]["pairs_per_s"] for r in rounds]
        result[name] = {"settings": settings[name], "median_ratio": statistics.median(ratios), "ratios": ratios}
        print(f"{name}: 16 / 1 clients median {statistics.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f}x)")
    record = {**harness.run_header(), "model": model, "window_s": args.window, "settings": result, "rounds": rounds}
    harness.write_record(args.out or harness.RESULTS / "scaling.json", record)
    return 0


def overload(args) -> int:
    from service.settings import Settings

    defaults = Settings()
    payloads = bodies()
    log = Path(tempfile.mkdtemp(prefix="ifnet-overload-")) / "service.log"
    service = harness.Service(log=log)
    try:
        service.wait_ready()
        record = {**harness.run_header(), "model": service.model(), "request_timeout_s": defaults.request_timeout_s}
        asyncio.run(closed_loop(service.url, payloads, 16, 3.0))
        outcomes, seconds = asyncio.run(closed_loop(service.url, payloads, 16, args.capacity_seconds))
        capacity = summary(outcomes, seconds)["pairs_per_s"]
        rate = args.factor * capacity
        print(f"capacity {capacity:.2f} pairs/s; offering {rate:.2f}/s for {args.duration:.0f} s", flush=True)
        with Sampler(service) as sampler:
            outcomes, offered_s = asyncio.run(
                open_loop(service.url, payloads, rate, args.duration, defaults.request_timeout_s + 30)
            )
        accepted = [o for o in outcomes if o["status"] == "200"]
        record["overload"] = {
            "capacity_pairs_per_s": capacity,
            "offered_per_s": len(outcomes) / offered_s,
            "seconds": args.duration,
            **summary(outcomes, offered_s),
            "accepted_p99_ms": percentile_ms(accepted, "s", 99),
            # Under overload the generator's own pool holds some requests for seconds before they are sent.
            "accepted_p99_on_wire_ms": percentile_ms(accepted, "wire_s", 99),
            "rss_mb": rss_summary(np.array([(t, mb) for t, mb in sampler.rss if t >= 10.0])),  # once started
            "ready_during": dict(sampler.ready),
            "health_after": httpx.get(f"{service.url}/health", timeout=10, trust_env=False).json(),
        }
        print("overload:", {k: v for k, v in record["overload"].items() if k != "health_after"}, flush=True)
        record["sigterm"] = asyncio.run(sigterm_under_load(service, payloads, args.sigterm_after))
        print("sigterm:", record["sigterm"], flush=True)
    finally:
        service.stop()
    text = log.read_text()
    record["log"] = {"tracebacks": text.count("Traceback"), "batcher_drained": "batchers drained" in text}
    harness.write_record(args.out or harness.RESULTS / "overload.json", record)
    return 0


REPLACED = "ifnet_feature_matching_replaced_total "  # its series in /metrics (no labels)


def soak(args) -> int:
    payloads = bodies(real=True)
    settings = dict(entry.split("=", 1) for entry in args.setting)
    service = harness.Service(**settings)
    try:
        service.wait_ready()
        record = {**harness.run_header(), "model": service.model(), "clients": args.clients, "settings": settings}
        print(f"{args.clients} clients for {args.duration:.0f} s", flush=True)
        with Sampler(service, interval_s=1.0) as sampler:
            outcomes, seconds = asyncio.run(closed_loop(service.url, payloads, args.clients, args.duration))
        health = httpx.get(f"{service.url}/health", timeout=10, trust_env=False).json()
        metrics = httpx.get(f"{service.url}/metrics", timeout=10, trust_env=False).text
    finally:
        service.stop()
    rss = np.array(sampler.rss)
    minutes = []
    started = min(o["at"] for o in outcomes)
    for minute in range(round(seconds / 60)):
        inside = (rss[:, 0] >= 60 * minute) & (rss[:, 0] < 60 * (minute + 1))
        answered = [o for o in outcomes if 60 * minute <= o["at"] - started < 60 * (minute + 1)]
        minutes.append({"rss_mb_max": float(rss[inside, 1].max()), **summary(answered, 60.0)})
    record["soak"] = {
        "seconds": seconds,
        **summary(outcomes, seconds),
        "rss_mb": rss_summary(rss, slope_from_s=rss[-1, 0] / 2),
        "ready_during": dict(sampler.ready),
        "feature_matching_replaced": sum(
            float(line.split()[-1]) for line in metrics.splitlines() if line.startswith(REPLACED)
        ),
        "minutes": minutes,
        "health_after": health,
    }
    for index, minute in enumerate(minutes):
        print(
            f"minute {index + 1}: RSS max {minute['rss_mb_max']:.0f} MB, {minute['pairs_per_s']:.2f} pairs/s, "
            f"p99 {minute['p99_ms'] or 0:.0f} ms, {minute['statuses']}"
        )
    print("soak:", {k: v for k, v in record["soak"].items() if k not in ("minutes", "health_after")}, flush=True)
    harness.write_record(args.out or harness.RESULTS / "soak.json", record)
    return 0


async def sigterm_under_load(service: harness.Service, payloads: list[bytes], after_s: float) -> dict:
    """16 closed-loop clients; SIGTERM after `after_s`; what became of the requests in flight then."""
    signalled: list[float] = []

    async def terminate() -> None:
        await asyncio.sleep(after_s)
        signalled.append(time.perf_counter())
        service.process.terminate()

    (outcomes, _), _ = await asyncio.gather(
        closed_loop(service.url, payloads, 16, after_s + 60, stop=lambda: bool(signalled)),
        terminate(),
    )
    exit_code = await asyncio.to_thread(service.process.wait, 120)
    in_flight = [o for o in outcomes if o["at"] < signalled[0] < o["at"] + o["s"]]
    return {
        "in_flight": len(in_flight),
        "in_flight_statuses": dict(Counter(o["status"] for o in in_flight)),
        "after_statuses": dict(Counter(o["status"] for o in outcomes if o["at"] >= signalled[0])),
        "exit_code": exit_code,
        "exited_after_s": time.perf_counter() - signalled[0],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path)
    commands = parser.add_subparsers(dest="command", required=True)
    s = commands.add_parser("scaling", help="16 clients vs 1 in alternating windows")
    s.add_argument(
        "--setting", action="append", default=[], help="NAME=KEY=VALUE[,KEY=VALUE]: IFNET_* of one more server"
    )
    s.add_argument("--rounds", type=int, default=6)
    s.add_argument("--window", type=float, default=8.0, help="seconds per window")
    o = commands.add_parser("overload", help="factor x capacity, then SIGTERM under load")
    o.add_argument("--factor", type=float, default=2.0)
    o.add_argument("--duration", type=float, default=60.0)
    o.add_argument("--capacity-seconds", type=float, default=15.0)
    o.add_argument("--sigterm-after", type=float, default=5.0)
    k = commands.add_parser("soak", help="steady load for minutes, memory sampled")
    k.add_argument("--clients", type=int, default=4)
    k.add_argument("--duration", type=float, default=600.0)
    k.add_argument("--setting", action="append", default=[], help="KEY=VALUE: an IFNET_* setting of the server")
    args = parser.parse_args(argv)
    if args.command == "scaling":
        if not (1 <= args.rounds <= 30 and 2 <= args.window <= 60):
            parser.error("--rounds must be in [1, 30] and --window in [2, 60]")
        return scaling(args)
    if args.command == "soak":
        if not (1 <= args.clients <= 64 and 60 <= args.duration <= 3600):
            parser.error("--clients must be in [1, 64] and --duration in [60, 3600] s")
        if any("=" not in entry for entry in args.setting):
            parser.error("--setting takes KEY=VALUE, e.g. --setting workers=1")
        return soak(args)
    if not (0 < args.duration <= 300 and 0 < args.factor <= 10 and 0 < args.capacity_seconds <= 60):
        parser.error("--duration must be in (0, 300], --factor in (0, 10], --capacity-seconds in (0, 60]")
    return overload(args)


if __name__ == "__main__":
    sys.exit(main())
