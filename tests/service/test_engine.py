"""The ONNX Runtime engine: CPU count from affinity and cgroups, model loading and its failures,
metadata, and the rule that nothing in the service imports torch."""

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.cpus import available_cpus, cgroup_cpu_limit
from service.engine import ModelLoadError, OnnxEngine
from service.settings import Settings

REPO = Path(__file__).resolve().parents[2]


def write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_cgroup_v2_quota(tmp_path):
    write(tmp_path / "proc_cgroup", "0::/\n")
    write(tmp_path / "cg" / "cpu.max", "150000 100000\n")
    assert cgroup_cpu_limit(tmp_path / "cg", tmp_path / "proc_cgroup") == 1.5
    write(tmp_path / "cg" / "cpu.max", "max 100000\n")
    assert cgroup_cpu_limit(tmp_path / "cg", tmp_path / "proc_cgroup") is None


def test_cgroup_v2_nested_path_takes_the_tightest_quota(tmp_path):
    write(tmp_path / "proc_cgroup", "0::/kubepods/pod1/container\n")
    write(tmp_path / "cg" / "kubepods" / "cpu.max", "400000 100000\n")
    write(tmp_path / "cg" / "kubepods" / "pod1" / "container" / "cpu.max", "200000 100000\n")
    assert cgroup_cpu_limit(tmp_path / "cg", tmp_path / "proc_cgroup") == 2.0


def test_cgroup_v1_quota(tmp_path):
    write(tmp_path / "proc_cgroup", "4:memory:/x\n3:cpu,cpuacct:/\n")
    write(tmp_path / "cg" / "cpu,cpuacct" / "cpu.cfs_quota_us", "300000\n")
    write(tmp_path / "cg" / "cpu,cpuacct" / "cpu.cfs_period_us", "100000\n")
    assert cgroup_cpu_limit(tmp_path / "cg", tmp_path / "proc_cgroup") == 3.0
    write(tmp_path / "cg" / "cpu,cpuacct" / "cpu.cfs_quota_us", "-1\n")
    assert cgroup_cpu_limit(tmp_path / "cg", tmp_path / "proc_cgroup") is None


def test_no_cgroup_information(tmp_path):
    assert cgroup_cpu_limit(tmp_path / "cg", tmp_path / "missing") is None


def test_available_cpus_respects_the_affinity_mask():
    assert 1 <= available_cpus() <= len(os.sched_getaffinity(0))


@pytest.mark.parametrize(("quota", "expected"), [(None, 4), (2.0, 2), (2.9, 2), (1.5, 1), (0.5, 1)])
def test_a_fractional_cpu_quota_rounds_down_but_never_below_one(monkeypatch, quota, expected):
    """1.5 CPUs give one thread: a second would only take turns with the first."""
    import service.cpus

    monkeypatch.setattr(service.cpus.os, "sched_getaffinity", lambda pid: set(range(4)))
    monkeypatch.setattr(service.cpus, "cgroup_cpu_limit", lambda: quota)
    assert available_cpus() == expected


def test_engine_threads_follow_the_usable_cpus_unless_set(tiny_model):
    assert OnnxEngine(tiny_model).threads == available_cpus()
    engine = OnnxEngine(tiny_model, threads=1)
    assert engine.threads == 1
    assert engine.session.get_session_options().intra_op_num_threads == 1
    # its threads stop spinning when a call ends, leaving the CPUs to the refinement after it
    assert engine.session.get_session_options().get_session_config_entry("session.force_spinning_stop") == "1"
    # a call beside others gets a share of the threads (at least one); a lone call gets them all
    shared = OnnxEngine(tiny_model, threads=4, model_calls=2)
    assert (shared.threads, shared.threads_beside_others) == (4, 2)
    single = OnnxEngine(tiny_model, threads=1, model_calls=2)
    assert (single.threads, single.threads_beside_others) == (1, 1)
    # beside the calls of other workers too: a lone call gets all, any other its share of the service's
    worker = OnnxEngine(tiny_model, threads=4, model_calls=1, workers=2)
    assert (worker.threads, worker.threads_beside_others) == (4, 2)


def test_model_calls_are_capped_at_one_per_thread():
    assert Settings(threads=4, model_calls=2).model_calls == 2
    assert Settings(threads=1, model_calls=2).model_calls == 1  # two calls would only take turns
    assert Settings(workers=1, model_calls=16).model_calls == min(16, available_cpus())


def test_workers_threads_and_model_calls_follow_the_usable_cpus(monkeypatch):
    import service.settings

    monkeypatch.setattr(service.settings, "available_cpus", lambda: 4)
    assert (Settings().workers, Settings().threads, Settings().model_calls) == (4, 4, 1)
    one = Settings(workers=1, threads=2)
    assert (one.workers, one.threads, one.model_calls) == (1, 2, 2)


def test_a_lone_call_runs_on_every_thread_and_calls_beside_it_on_their_share(tiny_model):
    engine = OnnxEngine(tiny_model, threads=2, model_calls=2)
    used = []

    class Recording:  # stands in for an ORT session and records its thread count per call
        def __init__(self, session):
            self.session = session

        def run(self, outputs, feeds):
            used.append(self.session.get_session_options().intra_op_num_threads)
            if len(used) == 1:  # the first call is still running when the second starts
                engine.run(feeds["source"], feeds["target"])
            return self.session.run(outputs, feeds)

    engine._sessions = [Recording(session) for session in engine._sessions]
    source, target = (np.random.default_rng(seed).normal(size=(1, 64, 3)).astype(np.float32) for seed in (1, 2))
    engine.run(source, target)
    engine.run(source, target)  # alone again once both have finished
    assert used == [2, 1, 2]

    # a call of one request among others in flight in its process gets its share too
    engine.running.requests = 2
    engine.run(source, target)
    engine.running.requests = 1
    engine.run(source, target)
    assert used == [2, 1, 2, 1, 2]

    # a lone call beside its caller's own work (a draft's first call beside feature matching) gets a share
    engine.run(source, target, beside=True)
    assert used == [2, 1, 2, 1, 2, 1]


@pytest.mark.anyio
async def test_the_service_counts_its_requests_in_flight_where_its_engines_see_them(tiny_model):
    from service.state import ServiceState

    engine = OnnxEngine(tiny_model, threads=2, model_calls=2)
    state = ServiceState(Settings(workers=1, threads=2))
    state.serve([engine])
    state.in_flight += 3
    assert engine.running.requests == 3 and state.in_flight == 3


def test_metadata_is_read(tiny_model):
    info = OnnxEngine(tiny_model).info
    assert (info.name, info.preset, info.network_points, info.opset) == ("object", "tiny-test", 64, "17")  # its file
    assert info.min_network_points == 16
    assert info.version == "0" * 12 and info.config == {"num_points": 64} and len(info.file_sha256) == 64
    assert [spec.name for spec in info.inputs] == ["source", "target"]
    assert [spec.datatype for spec in info.outputs] == ["FP32", "FP32"]


def test_missing_metadata_falls_back_to_768_points_with_a_warning(tmp_path, caplog, tiny_model_builder):
    path = tiny_model_builder(tmp_path / "bare.onnx", with_metadata=False)
    with caplog.at_level(logging.WARNING, logger="service.engine"):
        info = OnnxEngine(path).info
    assert info.network_points == 768 and info.name == "bare" and info.weights_sha256 is None
    assert info.min_network_points == 768, "without the record only the native count is known to run"
    assert info.version == info.file_sha256[:12]
    assert "no `num_points` metadata" in caplog.text and "no `min_points` metadata" in caplog.text


@pytest.mark.parametrize(("key", "value"), [("num_points", "many"), ("min_points", "0")])
def test_a_bad_point_count_in_the_metadata_fails_loading(tmp_path, tiny_model_builder, key, value):
    onnx = pytest.importorskip("onnx")
    path = tiny_model_builder(tmp_path / "bad.onnx")
    model = onnx.load(str(path))
    next(prop for prop in model.metadata_props if prop.key == key).value = value
    onnx.save(model, str(path))
    with pytest.raises(ModelLoadError, match=rf"metadata {key}='{value}' is not a positive integer"):
        OnnxEngine(path)


def test_a_missing_model_file_fails_with_its_path(tmp_path):
    with pytest.raises(ModelLoadError, match=r"nowhere\.onnx does not exist: set IFNET_MODEL_PATH"):
        OnnxEngine(tmp_path / "nowhere.onnx")


def test_a_corrupt_model_file_fails_clearly(tmp_path):
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x07 definitely not a protobuf" * 10)
    with pytest.raises(ModelLoadError, match="could not be loaded by onnxruntime"):
        OnnxEngine(corrupt)


def test_a_model_with_other_inputs_is_refused(tmp_path):
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["points"], ["features"])],
        "other",
        [helper.make_tensor_value_info("points", TensorProto.FLOAT, [1, 3])],
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, [1, 3])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(tmp_path / "other.onnx"))
    with pytest.raises(ModelLoadError, match="not an IFNet registration export"):
        OnnxEngine(tmp_path / "other.onnx")


@pytest.mark.anyio
async def test_app_startup_fails_without_a_model(tmp_path):
    from service.app import create_app

    app = create_app(Settings(model_path=tmp_path / "missing.onnx"))
    with pytest.raises(ModelLoadError, match="missing.onnx does not exist"):
        async with app.router.lifespan_context(app):
            pass


def test_settings_come_from_the_environment(monkeypatch):
    monkeypatch.setenv("IFNET_MAX_BATCH_SIZE", "6")
    monkeypatch.setenv("IFNET_MAX_BATCH_DELAY_MS", "2.5")
    monkeypatch.setenv("IFNET_API_KEY", "k")
    monkeypatch.setenv("IFNET_THREADS", "3")
    monkeypatch.setenv("IFNET_MODEL_CALLS", "2")
    settings = Settings()
    assert (settings.max_batch_size, settings.max_batch_delay_ms, settings.threads) == (6, 2.5, 3)
    assert settings.model_calls == 2
    assert settings.api_key.get_secret_value() == "k"
    assert settings.model_repository == REPO / "service" / "models" and settings.model_path is None
    assert Settings(max_batch_size=2).max_batch_size == 2  # explicit values win over the environment
    monkeypatch.setenv("IFNET_API_KEY", "")
    assert Settings().api_key is None  # an empty key (an absent optional secret) means no key


def test_the_service_never_imports_torch():
    """Import every service module (and build the app) with torch made unimportable."""
    code = (
        "import sys\n"
        "class NoTorch:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch' or name.startswith('torch.'):\n"
        "            raise ImportError('torch is not installed in the serving image')\n"
        "sys.meta_path.insert(0, NoTorch())\n"
        "import pkgutil, importlib, service\n"
        "for module in pkgutil.iter_modules(service.__path__):\n"
        "    importlib.import_module('service.' + module.name)\n"
        "from service.app import create_app\n"
        "create_app().openapi()\n"
        "assert 'torch' not in sys.modules\n"
        "print('ok')\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"
