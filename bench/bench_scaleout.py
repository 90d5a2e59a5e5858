"""Scale-out benchmark: registration throughput of 1 vs N replicas behind nginx (compose profile `scaleout`).

For each replica count the compose project is started (`--scale ifnet-replica=N`, each replica
limited to IFNET_REPLICA_CPUS CPUs and so to that many ONNX Runtime threads), the balancer's /ready
is awaited, a warm-up load is sent, then a closed-loop load of `--concurrency` asyncio clients
(httpx) POSTs pre-encoded /register requests to 127.0.0.1 for `--duration` seconds. Reported:
pairs per second, latency p50/p95/p99, errors, the share each replica served, and the machine's
load average. Every container is removed by id afterwards.

    python bench/bench_scaleout.py                       # 1 then 2 replicas, 60 s each
    python bench/bench_scaleout.py --replicas 1 2 --repeats 2 --duration 90

Needs Docker (../shared/tools/docker-base.sh docker/ca starts it here) and the images; `--build`
(or a missing image) builds them with the classic builder.
"""

import argparse
import asyncio
import json
import os
import platform
import re
import shutil
import socket
import statistics
import subprocess
import sys
import time
import uuid
from collections import Counter
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DOCKER_ENV = {**os.environ, "DOCKER_BUILDKIT": "0", "COMPOSE_DOCKER_CLI_BUILD": "0"}


@dataclass
class RunResult:
    replicas: int
    repeat: int
    duration_s: float
    completed: int
    errors: int
    pairs_per_s: float
    p50_ms: float | None
    p95_ms: float | None
    p99_ms: float | None
    by_replica: dict[str, int] = field(default_factory=dict)
    statuses: dict[str, int] = field(default_factory=dict)
    loadavg_before: str = ""
    loadavg_after: str = ""
    replica_memory: list[str] = field(default_factory=list)
    model_version: str | None = None
    startup_s: float = 0.0
    ort_threads: list[int] = field(default_factory=list)  # per replica, from its start-up log
    replica_cpus_used: float = 0.0  # CPUs the replicas actually got during the measurement
    host_cpus_busy: float = 0.0  # CPUs busy machine-wide (replicas, nginx, load generator, anything else)


# ---------------------------------------------------------------- docker helpers


def sh(args: list[str], timeout: float, env: dict | None = None, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(
        args, cwd=ROOT, env=env or DOCKER_ENV, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL
    )
    if check and done.returncode != 0:
        raise RuntimeError(f"exit {done.returncode}: {' '.join(args)}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return done


def compose_command() -> list[str]:
    if subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=30).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise SystemExit("neither `docker compose` nor `docker-compose` is installed")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def ensure_images(image: str, lb_image: str, build: bool) -> None:
    for tag, args in ((image, ["."]), (lb_image, ["-f", "docker/nginx.Dockerfile", "docker"])):
        missing = sh(["docker", "image", "inspect", tag], timeout=30, check=False).returncode != 0
        if build or missing:
            print(f"building {tag} ...", flush=True)
            started = time.monotonic()
            sh(["docker", "build", "-t", tag, *args], timeout=1800)
            print(f"built {tag} in {time.monotonic() - started:.0f} s", flush=True)


def container_cpu_seconds(container_id: str) -> float:
    """CPU time a container has used so far, from its cgroup (v2 cpu.stat or v1 cpuacct)."""
    script = "cat /sys/fs/cgroup/cpu.stat 2>/dev/null || cat /sys/fs/cgroup/cpuacct/cpuacct.usage"
    text = sh(["docker", "exec", container_id, "sh", "-c", script], timeout=30).stdout
    for line in text.splitlines():
        if line.startswith("usage_usec "):
            return int(line.split()[1]) / 1e6
    return int(text.split()[0]) / 1e9


def host_busy_seconds() -> float:
    """CPU time the whole machine has spent busy (not idle or waiting for I/O), from /proc/stat."""
    fields = [int(value) for value in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    return (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")


def loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


# ---------------------------------------------------------------- load


def make_bodies(count: int, points: int, seed: int = 0) -> list[bytes]:
    """Pre-encoded /register bodies: random smooth-ish clouds, each with a random rigid motion."""
    rng = np.random.default_rng(seed)
    bodies = []
    for _ in range(count):
        source = rng.normal(size=(points, 3)) * np.array([1.0, 0.6, 0.3])
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        rotation = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        target = source @ rotation.T + rng.normal(scale=0.2, size=3)
        bodies.append(json.dumps({"source": source.round(6).tolist(), "target": target.round(6).tolist()}).encode())
    return bodies


async def drive(base_url: str, bodies: list[bytes], concurrency: int, duration_s: float) -> tuple[list, float]:
    """Closed loop: `concurrency` clients, each sending its next request when the last one returns."""
    samples: list[tuple[float, int, str]] = []  # (latency s, status, upstream)
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    headers = {"content-type": "application/json"}
    async with httpx.AsyncClient(base_url=base_url, limits=limits, timeout=120, trust_env=False) as client:
        started = time.perf_counter()
        deadline = started + duration_s

        async def worker(index: int) -> None:
            turn = index
            while time.perf_counter() < deadline:
                body = bodies[turn % len(bodies)]
                turn += concurrency
                sent = time.perf_counter()
                try:
                    response = await client.post("/register", content=body, headers=headers)
                    status, upstream = response.status_code, response.headers.get("x-upstream", "?")
                except httpx.HTTPError as error:
                    status, upstream = 0, type(error).__name__
                samples.append((time.perf_counter() - sent, status, upstream))

        await asyncio.gather(*(worker(i) for i in range(concurrency)))
        elapsed = time.perf_counter() - started
    return samples, elapsed


def wait_ready(base_url: str, timeout: float) -> float:
    started = time.monotonic()
    with httpx.Client(trust_env=False, timeout=5) as client:
        while time.monotonic() - started < timeout:
            try:
                if client.get(f"{base_url}/ready").status_code == 200:
                    return time.monotonic() - started
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
    raise RuntimeError(f"{base_url}/ready not 200 within {timeout:.0f} s")


def percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


# ---------------------------------------------------------------- one configuration


def run_config(args, replicas: int, repeat: int, bodies: list[bytes]) -> RunResult:
    compose = compose_command()
    port = free_port()
    project = f"ifnetbench{uuid.uuid4().hex[:8]}"
    env = {
        **DOCKER_ENV,
        "IFNET_IMAGE": args.image,
        "IFNET_LB_IMAGE": args.lb_image,
        "IFNET_LB_PORT": str(port),
        "IFNET_BIND": "127.0.0.1",  # the balancer on loopback only, whatever the environment or .env say
        "IFNET_REPLICA_CPUS": str(args.replica_cpus),
    }
    base = [*compose, "-p", project, "-f", str(ROOT / "docker-compose.yml")]
    ids: set[str] = set()
    try:
        started = time.monotonic()
        up = ["--profile", "scaleout", "up", "-d", "--no-build", "--scale", f"ifnet-replica={replicas}"]
        sh([*base, *up, "ifnet-replica", "ifnet-lb"], timeout=600, env=env)
        ids.update(sh([*base, "ps", "-q"], timeout=60, env=env).stdout.split())
        base_url = f"http://127.0.0.1:{port}"
        wait_ready(base_url, 300)
        startup_s = time.monotonic() - started
        with httpx.Client(trust_env=False, timeout=120) as client:
            model = client.post(f"{base_url}/register", content=bodies[0], headers={"content-type": "application/json"})
            model.raise_for_status()
            model_version = model.json().get("model", {}).get("version")
        print(f"  {replicas} replica(s) up in {startup_s:.0f} s; warming up {args.warmup:.0f} s", flush=True)
        asyncio.run(drive(base_url, bodies, args.concurrency, args.warmup))
        replica_ids = sh([*base, "ps", "-q", "ifnet-replica"], timeout=60, env=env).stdout.split()
        threads = []
        for cid in replica_ids:
            log = sh(["docker", "logs", cid], timeout=60)
            found = re.search(r"with (\d+) ORT threads", log.stdout + log.stderr)
            threads.append(int(found.group(1)) if found else -1)
        before = loadavg()
        cpu_before = sum(container_cpu_seconds(cid) for cid in replica_ids)
        host_before = host_busy_seconds()
        samples, elapsed = asyncio.run(drive(base_url, bodies, args.concurrency, args.duration))
        host_used = host_busy_seconds() - host_before
        cpu_used = sum(container_cpu_seconds(cid) for cid in replica_ids) - cpu_before
        after = loadavg()
        stats = sh(["docker", "stats", "--no-stream", "--format", "{{.MemUsage}}", *replica_ids], timeout=60)
        ok = [latency * 1000 for latency, status, _ in samples if status == 200]
        return RunResult(
            replicas=replicas,
            repeat=repeat,
            duration_s=round(elapsed, 2),
            completed=len(ok),
            errors=len(samples) - len(ok),
            pairs_per_s=round(len(ok) / elapsed, 3),
            p50_ms=percentile(ok, 50),
            p95_ms=percentile(ok, 95),
            p99_ms=percentile(ok, 99),
            by_replica=dict(Counter(upstream for _, status, upstream in samples if status == 200)),
            statuses={str(k): v for k, v in Counter(status for _, status, _ in samples).items()},
            loadavg_before=before,
            loadavg_after=after,
            replica_memory=[line.split("/")[0].strip() for line in stats.stdout.splitlines()],
            model_version=model_version,
            startup_s=round(startup_s, 1),
            ort_threads=threads,
            replica_cpus_used=round(cpu_used / elapsed, 3),
            host_cpus_busy=round(host_used / elapsed, 3),
        )
    finally:
        try:
            ids.update(sh([*base, "ps", "-q"], timeout=60, env=env, check=False).stdout.split())
        finally:
            if ids:
                sh(["docker", "rm", "-f", "-v", *sorted(ids)], timeout=120, check=False)
            sh([*base, "down", "-v", "--remove-orphans"], timeout=180, env=env, check=False)


# ---------------------------------------------------------------- report


def fmt(value: float | None, digits: int = 0) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


TITLE = """# Scale-out benchmark: replicas behind nginx

Written by `bench/bench_scaleout.py` (compose profile `scaleout`: N replicas of the service behind
nginx on one machine). Each section is one invocation, newest last.

"""


def write_report(path: Path, args, results: list[RunResult], compose: list[str], append: bool) -> str:
    by_n: dict[int, list[RunResult]] = {}
    for result in results:
        by_n.setdefault(result.replicas, []).append(result)
    rows = [
        "| replicas | run | pairs/s | p50 ms | p95 ms | p99 ms | ok | errors | served per replica | "
        "CPUs the replicas got | CPUs busy, whole machine | pairs per replica CPU-s | replica memory | load avg |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---|---|",
    ]
    for result in results:
        share = ", ".join(f"{count}" for _, count in sorted(result.by_replica.items()))
        per_cpu = result.pairs_per_s / result.replica_cpus_used if result.replica_cpus_used else None
        rows.append(
            f"| {result.replicas} | {result.repeat} | {result.pairs_per_s:.2f} | {fmt(result.p50_ms)} | "
            f"{fmt(result.p95_ms)} | {fmt(result.p99_ms)} | {result.completed} | {result.errors} | {share} | "
            f"{result.replica_cpus_used:.2f} | {result.host_cpus_busy:.2f} | {fmt(per_cpu, 2)} | "
            f"{', '.join(result.replica_memory)} | {result.loadavg_before} → {result.loadavg_after} |"
        )
    summary = []
    means = {n: statistics.mean(r.pairs_per_s for r in runs) for n, runs in sorted(by_n.items())}
    if 1 in means and len(means) > 1:
        for n, mean in means.items():
            if n != 1:
                summary.append(f"- {n} replicas: {mean:.2f} pairs/s vs {means[1]:.2f} with 1 ({mean / means[1]:.2f}x).")
    cpu = os.cpu_count()
    docker_version = sh(
        ["docker", "version", "--format", "{{.Server.Version}}"], timeout=30, check=False
    ).stdout.strip()
    command = " ".join(["python", "bench/bench_scaleout.py", *sys.argv[1:]])
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    text = "\n".join(
        [
            f"## {when}: {' vs '.join(str(n) for n in sorted(by_n))} replicas of {args.replica_cpus:g} CPU each",
            "",
            f"Command: `{command}`.",
            "",
            f"- Machine: {cpu} CPUs, {platform.machine()}, Docker {docker_version}, compose: `{' '.join(compose)}`.",
            f"- Each replica: `--cpus {args.replica_cpus:g}`, ONNX Runtime threads per replica (from its log, "
            f"-1 = not found): {sorted({t for r in results for t in r.ort_threads})}; image `{args.image}`, "
            f"model version `{results[0].model_version if results else '?'}`.",
            f"- Load: {args.concurrency} closed-loop asyncio clients (httpx) on 127.0.0.1 through nginx, "
            f"{args.duration:.0f} s measured after {args.warmup:.0f} s of warm-up; {args.bodies} pre-encoded "
            f"JSON pairs of {args.points} points per cloud, cycled. The same load and balancer for every "
            "replica count; only the number of replicas changes.",
            "- The load generator, nginx and the replicas share this machine's CPUs with whatever else runs "
            'on it: "CPUs the replicas got" is their cgroup CPU time over the measured seconds, "CPUs busy" '
            "the whole machine's (from /proc/stat). The numbers are what this machine gave at that time.",
            *([f"- Note: {args.note}"] if args.note else []),
            "",
            *rows,
            "",
            *(summary or ["- Only one replica count was run."]),
            "",
            "Raw results:",
            "",
            "```json",
            json.dumps([asdict(result) for result in results], indent=1),
            "```",
            "",
        ]
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    if append and path.exists():
        path.write_text(path.read_text().rstrip("\n") + "\n\n" + text)
    else:
        path.write_text(TITLE + text)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--replicas", type=int, nargs="+", default=[1, 2], help="replica counts to run, in order")
    parser.add_argument("--repeats", type=int, default=1, help="runs of the whole sequence (interleaved)")
    parser.add_argument("--duration", type=float, default=60.0, help="measured seconds per run (max 600)")
    parser.add_argument("--warmup", type=float, default=10.0, help="unmeasured load before each run")
    parser.add_argument("--concurrency", type=int, default=4, help="requests in flight")
    parser.add_argument("--points", type=int, default=1024, help="points per cloud")
    parser.add_argument("--bodies", type=int, default=16, help="distinct pre-encoded pairs")
    parser.add_argument("--replica-cpus", type=float, default=1.0, help="CPU limit (and threads) of each replica")
    parser.add_argument("--image", default="ifnet-serve:latest")
    parser.add_argument("--lb-image", default="ifnet-serve-lb:latest")
    parser.add_argument("--build", action="store_true", help="(re)build both images first")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks-scaleout.md")
    parser.add_argument("--note", default="", help="a remark for the report, e.g. what else ran on the machine")
    parser.add_argument("--append", action="store_true", help="add a section to --out instead of replacing it")
    args = parser.parse_args(argv)
    if not 0 < args.duration <= 600 or not 0 <= args.warmup <= 120 or not 1 <= args.concurrency <= 64:
        parser.error("--duration must be in (0, 600], --warmup in [0, 120], --concurrency in [1, 64]")
    if subprocess.run(["docker", "info"], capture_output=True, timeout=30).returncode != 0:
        print("Docker does not answer: run ../shared/tools/docker-base.sh docker/ca first (as root)", file=sys.stderr)
        return 2
    compose = compose_command()
    ensure_images(args.image, args.lb_image, args.build)
    bodies = make_bodies(args.bodies, args.points)
    results = []
    for repeat in range(1, args.repeats + 1):
        for replicas in args.replicas:
            print(f"run {repeat}: {replicas} replica(s)", flush=True)
            result = run_config(args, replicas, repeat, bodies)
            results.append(result)
            print(
                f"  {result.pairs_per_s:.2f} pairs/s, p50 {fmt(result.p50_ms)} ms, p95 {fmt(result.p95_ms)} ms, "
                f"{result.errors} errors, per replica {result.by_replica}; the replicas got "
                f"{result.replica_cpus_used:.2f} CPUs, the machine was {result.host_cpus_busy:.2f} CPUs busy",
                flush=True,
            )
    print(write_report(args.out, args, results, compose, args.append))
    return 0


if __name__ == "__main__":
    sys.exit(main())
