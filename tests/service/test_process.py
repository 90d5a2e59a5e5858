"""The real thing: `python -m service` under uvicorn on a free loopback port, the command-line
client against it, graceful shutdown on SIGTERM, and a clear failure without a model."""

import http.client
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest
from conftest import free_port, metric_values, service_process

from service.client import RegistrationClient, RegistrationError
from service.formats import read_cloud_file, write_ply

REPO = Path(__file__).resolve().parents[2]


def run_client(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-m", "service.client", *args], capture_output=True, text=True, env=env, timeout=120
    )


def test_server_and_command_line_client(tmp_path, tiny_model):
    rng = np.random.default_rng(0)
    source = rng.normal(size=(300, 3))
    target = source @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T + [1.0, 2.0, 3.0]
    write_ply(tmp_path / "source.ply", source)
    np.save(tmp_path / "target.npy", target)
    (tmp_path / "notes.txt").write_text("not a cloud")

    with service_process(tmp_path, tiny_model, max_batch_size="2") as (process, url, log):
        assert httpx.get(f"{url}/health").json()["ready"] is True
        printed = run_client(str(tmp_path / "source.ply"), str(tmp_path / "target.npy"), "--url", url)
        as_json = run_client(
            str(tmp_path / "source.ply"),
            str(tmp_path / "target.npy"),
            "--url",
            url,
            "--refine",
            "--json",
            "--output",
            str(tmp_path / "aligned.ply"),
        )
        refused = run_client(str(tmp_path / "notes.txt"), str(tmp_path / "target.npy"), "--url", url)
        with RegistrationClient(url) as client:
            from_arrays = client.register(source, target.astype(np.float32), seed=0, refine=True)
            assert client.ready()
            with pytest.raises(RegistrationError, match=r"HTTP 422: source: .*\(request id [0-9a-f]{32}\)"):
                client.register(source[:, :2], target)
        posted_json = httpx.post(
            f"{url}/register",
            json={"source": source.tolist(), "target": target.astype(np.float32).tolist(), "seed": 0, "refine": True},
        ).json()

    assert printed.returncode == 0, printed.stderr
    lines = printed.stdout.splitlines()
    assert lines[0] == "transform (source -> target):" and len(lines[1].split()) == 4
    assert lines[5].startswith("fitness ")
    assert as_json.returncode == 0, as_json.stderr
    result = json.loads(as_json.stdout)
    transform = np.asarray(result["transform"])
    assert result["refinement"]["iterations"] >= 1
    aligned = read_cloud_file(tmp_path / "aligned.ply")
    np.testing.assert_allclose(aligned, source @ transform[:3, :3].T + transform[:3, 3], atol=1e-5)
    assert refused.returncode == 1 and "HTTP 415" in refused.stderr
    assert re.search(r"\(request id [0-9a-f]{32}\)$", refused.stderr.strip())  # to quote in a report
    np.testing.assert_allclose(from_arrays["transform"], posted_json["transform"], atol=1e-9)  # the same request
    assert from_arrays["refinement"]["iterations"] >= 1  # the options arrived


def test_the_command_line_client_names_what_went_wrong(tmp_path):
    np.save(tmp_path / "cloud.npy", np.random.default_rng(0).normal(size=(50, 3)))
    (tmp_path / "init.txt").write_text("not a matrix")
    cloud = str(tmp_path / "cloud.npy")
    down = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    unreachable = run_client(cloud, cloud, "--url", down)
    bad_init = run_client(cloud, cloud, "--url", down, "--init", str(tmp_path / "init.txt"))
    assert unreachable.returncode == 1
    assert f"cannot reach the service at {down}" in unreachable.stderr and "--url" in unreachable.stderr
    assert bad_init.returncode == 1 and f"--init {tmp_path / 'init.txt'}: not a 4x4 matrix" in bad_init.stderr
    assert "Traceback" not in unreachable.stderr + bad_init.stderr


def test_the_command_line_client_sends_its_options(tmp_path, monkeypatch, capsys):
    from service import client

    sent = {}

    def register_files(self, source, target, **options):
        sent.update(options)
        return {"transform": np.eye(4).tolist(), "fitness": 1.0, "inlier_rmse": 0.0, "fitness_threshold": 0.1,
                "verified": False, "reason": "low overlap", "stage": "features",
                "model": {"name": "indoor", "version": "0" * 12}, "timings_ms": {"total_ms": 1.0}}  # fmt: skip

    monkeypatch.setattr(client.RegistrationClient, "register_files", register_files)
    argv = [
        "s.ply",
        "t.ply",
        "--refine-distance",
        "0.25",
        "--network-points",
        "512",
        "--sampling",
        "random",
        "--seed",
        "3",
        "--method",
        "global",
        "--model",
        "indoor",
    ]
    assert client.main(argv) == 0
    assert sent == {
        "init": None,
        "refine": {"max_distance": 0.25},
        "network_points": 512,
        "sampling": "random",
        "seed": 3,
        "model": "indoor",
        "method": "global",
    }
    printed = capsys.readouterr().out
    assert printed.startswith("transform (source -> target):")
    assert "NOT verified: low overlap  (stage features)" in printed and "model indoor 000000000000" in printed


def test_sigterm_finishes_in_flight_requests_then_exits(tmp_path, tiny_model):
    # Clouds big enough that parsing and sampling keep each request busy for a while.
    rng = np.random.default_rng(1)
    clouds = [rng.normal(size=(12_000, 3)).tolist() for _ in range(2)]
    request = {"source": clouds[0], "target": clouds[1], "max_points": 1024}

    def post() -> int:
        return httpx.post(f"{url}/register", json=request, timeout=120).status_code

    with service_process(tmp_path, tiny_model, max_network_points="1024") as (process, url, log):
        with ThreadPoolExecutor(4) as pool:
            pending = [pool.submit(post) for _ in range(4)]
            for _ in range(3000):  # hang guard
                if httpx.get(f"{url}/health").json()["in_flight"] == 4:
                    break
                time.sleep(0.02)
            else:
                raise AssertionError("the four requests never were in flight together")
            process.send_signal(signal.SIGTERM)
            statuses = [future.result() for future in pending]
        exit_code = process.wait(timeout=60)

    assert statuses == [200, 200, 200, 200]
    # uvicorn re-raises the signal it caught once shutdown is complete, so the parent sees SIGTERM.
    assert exit_code in (0, -signal.SIGTERM)
    text = log.read_text()
    assert "batchers drained" in text and "Finished server process" in text


@pytest.mark.parametrize("workers", ["1", "2"])
def test_startup_fails_clearly_without_a_model(tmp_path, workers):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    missing = tmp_path / "missing.onnx"
    command = [sys.executable, "-m", "service", "--model-path", str(missing), "--port", str(free_port())]
    result = subprocess.run([*command, "--workers", workers], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 1
    assert f"cannot start: model file {missing} does not exist" in result.stderr and "Traceback" not in result.stderr


def metric_total(text: str, name: str, **labels: str) -> float:
    """The sum of a metric's samples in Prometheus text whose labels include `labels`."""
    wanted = set(labels.items())
    return sum(
        value for (sample, *pairs), value in metric_values(text).items() if sample == name and wanted <= set(pairs)
    )


def test_workers_share_the_port_and_metrics_add_them_up(tmp_path, tiny_model):
    rng = np.random.default_rng(2)
    source = rng.normal(size=(300, 3))
    request = {"source": source.tolist(), "target": (source + [0.1, 0.0, 0.0]).tolist(), "method": "ifnet"}

    def post(_) -> int:  # a connection of its own each, so that the kernel hands them to either worker
        return httpx.post(f"{url}/register", json=request, timeout=120).status_code

    # The supervisor makes its metrics folder under TMPDIR and removes it when it stops.
    with service_process(tmp_path, tiny_model, workers="2", env={"TMPDIR": str(tmp_path)}) as (process, url, log):
        (metrics,) = tmp_path.glob("ifnet-metrics-*")
        with ThreadPoolExecutor(8) as pool:
            statuses = list(pool.map(post, range(16)))
        scrapes = [httpx.get(f"{url}/metrics").text for _ in range(6)]
        writers = {path.stem.rsplit("_", 1)[1] for path in metrics.glob("counter_*.db")}
        process.send_signal(signal.SIGTERM)
        exit_code = process.wait(timeout=60)

    assert statuses == [200] * 16
    assert len(writers) == 2, f"the requests were not shared out: counters of {writers}"
    for scrape in scrapes:  # whichever worker answered, it counted both workers' answers
        assert metric_total(scrape, "ifnet_answers_total", model="object") == 16
        assert metric_total(scrape, "ifnet_ready") == 1
    # each scrape is counted once it is answered: the k-th sees the k - 1 before it, whoever served them
    assert [metric_total(s, "ifnet_http_requests_total", route="/metrics") for s in scrapes] == [0, 1, 2, 3, 4, 5]
    assert exit_code == 0 and not metrics.exists()
    assert log.read_text().count("batchers drained") == 2  # each worker drained its own


def burst(url: str, count: int) -> list[int]:
    """`count` connections opened together, then one GET /health on each: their status codes."""
    port = urlsplit(url).port
    connections = [http.client.HTTPConnection("127.0.0.1", port, timeout=120) for _ in range(count)]
    for connection in connections:
        connection.connect()
    statuses = []
    for connection in connections:
        connection.request("GET", "/health")
        response = connection.getresponse()
        response.read()
        statuses.append(response.status)
        connection.close()
    return statuses


def health_answers_per_worker(metrics: Path) -> dict[int, float]:
    """Each worker's count of /health answers, from its own counter file in the metrics folder."""
    from prometheus_client.mmap_dict import MmapedDict

    answers = {}
    for path in metrics.glob("counter_*.db"):
        samples = [(json.loads(key), value) for key, value, *_ in MmapedDict.read_all_values_from_file(str(path))]
        answers[int(path.stem.rsplit("_", 1)[1])] = sum(
            value
            for (_, name, labels, *_), value in samples
            if name == "ifnet_http_requests_total" and labels["route"] == "/health"
        )
    return answers


def worker_pids(supervisor: int) -> set[int]:
    children = Path(f"/proc/{supervisor}/task/{supervisor}/children").read_text().split()
    return {int(pid) for pid in children if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()}


def await_listeners(url: str, count: int) -> None:
    """Until `count` sockets listen on the url's port: /ready answers as soon as one worker does."""
    port = f":{urlsplit(url).port:04X}"
    for _ in range(600):
        rows = [line.split() for line in Path("/proc/net/tcp").read_text().splitlines()[1:]]
        if sum(local.endswith(port) and state == "0A" for _, local, _, state, *_ in rows) >= count:  # 0A: LISTEN
            return
        time.sleep(0.1)
    raise AssertionError(f"fewer than {count} sockets listen on {url}")


def test_a_burst_of_connections_is_dealt_out_to_both_workers(tmp_path, tiny_model):
    # Each worker listens on a socket of its own: on one shared socket, the first worker to wake
    # accepted nearly all of a burst and the other idled.
    with service_process(tmp_path, tiny_model, workers="2", env={"TMPDIR": str(tmp_path)}) as (process, url, log):
        (metrics,) = tmp_path.glob("ifnet-metrics-*")
        await_listeners(url, 2)
        statuses = burst(url, 32)
        answers = health_answers_per_worker(metrics)
    assert statuses == [200] * 32
    assert len(answers) == 2 and min(answers.values()) >= 6, answers  # by chance: 1 run in 10,000


def test_a_dead_worker_is_replaced_on_its_socket_and_sighup_is_ignored(tmp_path, tiny_model):
    with service_process(tmp_path, tiny_model, workers="2", env={"TMPDIR": str(tmp_path)}) as (process, url, log):
        (metrics,) = tmp_path.glob("ifnet-metrics-*")
        await_listeners(url, 2)
        first = worker_pids(process.pid)
        os.kill(min(first), signal.SIGKILL)
        # The connections its socket takes meanwhile wait there for the replacement.
        statuses = burst(url, 32)
        (replacement,) = worker_pids(process.pid) - first
        answers = health_answers_per_worker(metrics)
        process.send_signal(signal.SIGHUP)  # uvicorn's restart would hand sockets out anew: ignored
        time.sleep(1)
        after = burst(url, 4)
        workers = worker_pids(process.pid)
    assert statuses == [200] * 32 and after == [200] * 4
    assert answers.get(replacement, 0) >= 1, answers
    assert workers == (first - {min(first)}) | {replacement}
    text = log.read_text()
    assert f"Worker [{min(first)}] died; starting another on its socket." in text
    assert "Ignored SIGHUP: restart the service to change its workers." in text


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_port_in_use_fails_the_start_clearly(tmp_path, tiny_model, workers):
    # Held as another service's worker holds it (SO_REUSEPORT), which must not make it shareable.
    with socket.socket() as holder:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        command = [sys.executable, "-m", "service", "--model-path", str(tiny_model), "--port", str(port)]
        result = subprocess.run([*command, "--workers", workers], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 1
    assert f"cannot listen on 127.0.0.1:{port} (Address already in use): stop what holds that port" in result.stderr


@pytest.mark.parametrize("value", ["0", "lots"])
def test_invalid_settings_are_reported(tmp_path, value):
    env = {**os.environ, "PYTHONPATH": str(REPO), "IFNET_MAX_BATCH_SIZE": value}
    result = subprocess.run([sys.executable, "-m", "service"], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 2 and "max_batch_size" in result.stderr
