"""The data pipeline, a tiny training run with checkpoint and resume, and the shipped weights."""

import csv
import json
import os

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the training tests need torch")

from scipy.spatial import cKDTree  # noqa: E402

from model.artifacts import DEFAULT_WEIGHTS  # noqa: E402
from model.cli import UserError  # noqa: E402
from model.geometry import apply_transform, disjoint_halves, matrix_to_euler  # noqa: E402
from model.training.data import Protocol, RegistrationPairs, load_split, make_pair, synthetic_shape  # noqa: E402
from model.training.train import main as train_main  # noqa: E402


@pytest.fixture(scope="module")
def shapes() -> np.ndarray:
    return np.stack([synthetic_shape(np.random.default_rng(i)) for i in range(12)])


@pytest.mark.parametrize(("noise", "count"), [("clean", 768), ("jitter", 768), ("outliers", 868)])
def test_pairs_follow_the_protocol(shapes, noise, count):
    pair = make_pair(shapes[0], Protocol(noise=noise), np.random.default_rng(0))
    assert pair["source"].shape == (count, 3) and pair["target"].shape == (count, 3)
    assert pair["source"].dtype == np.float32
    rotation, translation = pair["rotation"].astype(np.float64), pair["translation"]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
    assert np.all((matrix_to_euler(rotation) >= -1e-4) & (matrix_to_euler(rotation) <= 45 + 1e-4))
    assert np.all(np.abs(translation) <= 0.5)


def test_target_is_a_rigid_motion_of_the_shape(shapes):
    """Clean targets are exact images of shape points; the two crops overlap only partly."""
    pair = make_pair(shapes[1], Protocol(), np.random.default_rng(1))
    shape_tree = cKDTree(shapes[1].astype(np.float64))
    back = apply_transform(pair["target"] - pair["translation"], pair["rotation"].T.astype(np.float64), np.zeros(3))
    assert shape_tree.query(back)[0].max() < 1e-5
    assert shape_tree.query(pair["source"])[0].max() < 1e-6
    shared = cKDTree(pair["source"]).query(back)[0] < 1e-5
    assert 0.3 < shared.mean() < 1.0  # partial-to-partial


def test_pairs_are_seeded_by_index(shapes):
    a, b = RegistrationPairs(shapes, seed=3), RegistrationPairs(shapes, seed=3)
    for key in ("source", "target", "rotation", "translation"):
        assert torch.equal(a[5][key], b[5][key])
    assert not torch.equal(a[5]["rotation"], a[6]["rotation"])
    b.epoch = 1  # training draws new motions each epoch
    assert not torch.equal(a[5]["rotation"], b[5]["rotation"])


def test_mixed_protocols_give_both_kinds_of_pair(shapes):
    """Clean sources are exact shape points; jittered ones are not. A mix yields both, by seed."""
    pairs = RegistrationPairs(shapes, [Protocol(noise="clean"), Protocol(noise="jitter")], seed=5)
    trees = [cKDTree(shape.astype(np.float64)) for shape in shapes]
    jittered = [trees[i].query(pairs[i]["source"].numpy())[0].max() > 1e-5 for i in range(len(shapes))]
    assert 0 < sum(jittered) < len(shapes), jittered
    again = RegistrationPairs(shapes, [Protocol(noise="clean"), Protocol(noise="jitter")], seed=5)
    assert torch.equal(pairs[3]["source"], again[3]["source"])


@pytest.mark.parametrize("sigma", [0.002, 0.01])
def test_jitter_moves_every_point_by_at_most_five_sigma(shapes, sigma):
    pair = make_pair(shapes[2], Protocol(noise="jitter", jitter_sigma=sigma), np.random.default_rng(2))
    offsets = cKDTree(shapes[2].astype(np.float64)).query(pair["source"])[0]
    assert offsets.max() <= 5 * sigma * np.sqrt(3) + 1e-6
    assert np.median(offsets) > 0.5 * sigma  # every point moved, not just a few


def test_pairs_carry_their_clouds_before_noise(shapes):
    """The noise-free clouds (a teacher's input) are the jittered clouds' points before jitter, one to one."""
    clean = make_pair(shapes[3], Protocol(), np.random.default_rng(3))
    jittered = make_pair(shapes[3], Protocol(noise="jitter"), np.random.default_rng(3))
    for cloud in ("source", "target"):
        np.testing.assert_array_equal(clean[f"noise_free_{cloud}"], clean[cloud])
        np.testing.assert_array_equal(jittered[f"noise_free_{cloud}"], clean[cloud])  # same seed, same crop
        offsets = np.linalg.norm(jittered[cloud] - jittered[f"noise_free_{cloud}"], axis=1)
        assert np.median(offsets) > 0.005 and offsets.max() <= 0.05 * np.sqrt(3) + 1e-6


def test_shared_jitter_keeps_exact_shared_points_off_the_shape(shapes):
    """The diagnostic variant: the clouds share noisy points exactly, unlike the protocol's jitter."""
    for shared in (True, False):
        pair = make_pair(shapes[4], Protocol(noise="jitter", shared_jitter=shared), np.random.default_rng(4))
        back = apply_transform(pair["target"] - pair["translation"], pair["rotation"].T.astype(np.float64), np.zeros(3))
        exact = cKDTree(pair["source"]).query(back)[0] < 1e-5
        assert (0.3 < exact.mean() < 1.0) if shared else not exact.any()
        assert np.median(cKDTree(shapes[4].astype(np.float64)).query(pair["source"])[0]) > 0.005
    with pytest.raises(ValueError, match="jitter noise only"):
        Protocol(noise="outliers", shared_jitter=True)


def test_disjoint_halves_split_a_cloud_without_a_common_point():
    cloud = synthetic_shape(np.random.default_rng(5), num_points=1001)
    first, second = disjoint_halves(cloud, np.random.default_rng(6))
    assert (len(first), len(second)) == (500, 501)
    assert not set(map(tuple, first)) & set(map(tuple, second))
    np.testing.assert_array_equal(np.unique(np.concatenate([first, second]), axis=0), np.unique(cloud, axis=0))
    again = disjoint_halves(cloud, np.random.default_rng(6))
    np.testing.assert_array_equal(again[0], first)


def test_training_jitter_sigma_reaches_the_pairs(shapes):
    from model.training.train import parse_args, training_pairs

    pairs = training_pairs(shapes, parse_args(["--noise", "jitter", "--jitter-sigma", "0.002"]), 768)
    offsets = np.concatenate([cKDTree(shapes[i]).query(pairs[i]["source"].numpy())[0] for i in range(4)])
    assert offsets.max() <= 5 * 0.002 * np.sqrt(3) + 1e-6  # the default sigma (0.01) would exceed this
    assert np.median(offsets) > 0.001


def test_a_smaller_network_gets_clouds_sampled_from_the_pair_and_the_teacher_the_whole_pair(shapes):
    whole, sampled = RegistrationPairs(shapes, seed=2)[3], RegistrationPairs(shapes, seed=2, network_points=384)[3]
    for key in ("source", "target"):
        assert sampled[key].shape == (384, 3)
        assert len(np.unique(sampled[key].numpy(), axis=0)) == 384
        assert cKDTree(whole[key].numpy()).query(sampled[key].numpy())[0].max() == 0.0  # points of the pair
        assert torch.equal(sampled[f"noise_free_{key}"], whole[f"noise_free_{key}"])
    assert torch.equal(sampled["rotation"], whole["rotation"])


def test_protocols_of_different_cloud_sizes_cannot_be_mixed(shapes):
    with pytest.raises(ValueError, match="one size"):
        RegistrationPairs(shapes, [Protocol(noise="clean"), Protocol(noise="outliers")])


@pytest.mark.slow
def test_tiny_training_run_checkpoints_and_resumes(tmp_path, shapes, capsys):
    np.savez(tmp_path / "modelnet10_train.npz", points=shapes)
    common = [
        "--preset",
        "fast",
        "--data-dir",
        str(tmp_path),
        "--out",
        str(tmp_path / "run"),
        "--batch-size",
        "2",
        "--val-shapes",
        "2",
        "--checkpoint-every",
        "2",
        "--threads",
        "1",
    ]
    train_main([*common, "--max-steps", "2"])
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    first = torch.load(checkpoint, weights_only=False)
    assert first["step"] == 2

    capsys.readouterr()
    train_main([*common, "--max-steps", "3"])
    assert "--max-steps 3 (checkpoint: 2)" in capsys.readouterr().out  # the schedule changed: say so
    second = torch.load(checkpoint, weights_only=False)
    assert second["step"] == 3
    changed = [k for k in first["model"] if not torch.equal(first["model"][k], second["model"][k])]
    assert changed, "resumed training did not update the weights"
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    assert [int(r["step"]) for r in rows] == [1, 2, 3]
    validated = [r for r in rows if r["val_rotation_deg"]]
    assert [int(r["step"]) for r in validated] == [2, 3]  # every checkpoint, clean and jittered
    assert all(float(r["val_jitter_rotation_deg"]) >= 0 for r in validated)
    seconds = [float(r["seconds"]) for r in rows]
    assert seconds == sorted(seconds), "the training clock must continue across a resume"
    assert (tmp_path / "run" / "losses.png").stat().st_size > 0


def save_random_network(path, seed: int):
    """A randomly initialised fast-preset network, saved as shipped weights are; returns it."""
    from model.ifnet import IFNet, preset

    torch.manual_seed(seed)
    network = IFNet(preset("fast"))
    torch.save({"model": network.state_dict(), "config": network.config.to_dict()}, path)
    return network


def train_briefly(tmp_path, shapes, *options: str) -> None:
    """A few steps of the fast preset on the synthetic shapes, on jittered pairs, into tmp_path/run."""
    np.savez(tmp_path / "modelnet10_train.npz", points=shapes)
    train_main(
        ["--preset", "fast", "--data-dir", str(tmp_path), "--out", str(tmp_path / "run"), "--batch-size", "2"]
        + ["--val-shapes", "2", "--threads", "1", "--noise", "jitter", *options]
    )


@pytest.mark.slow
def test_training_with_a_teacher_logs_its_consistency_loss(tmp_path, shapes):
    save_random_network(tmp_path / "teacher.pt", seed=5)
    train_briefly(tmp_path, shapes, "--max-steps", "2", "--teacher", str(tmp_path / "teacher.pt"))
    from model.training.ship import read_checkpoint, ship

    checkpoint = tmp_path / "run" / "checkpoint.pt"
    record = ship(read_checkpoint(checkpoint), checkpoint, tmp_path / "shipped.pt")
    assert "teacher consistency" in record["training"]["objective"], record["training"]
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    # A random student and a random teacher disagree by a good fraction of the unit-sphere clouds.
    assert all(float(r["teacher_consistency"]) > 0.01 for r in rows), rows


def test_a_later_leg_of_training_keeps_the_record_of_the_weights_it_started_from(tmp_path):
    """Shipping a run fine-tuned from shipped weights into the same file keeps their record inside the
    new one: the earlier legs' steps and hours are not lost."""
    from model.training.ship import ship

    weights = tmp_path / "ifnet-indoor.pt"
    network = save_random_network(weights, seed=3)
    earlier = {"file": weights.name, "sha256": "ab", "training": {"steps": 405, "hours_on_2_cpu_cores": 1.14}}
    weights.with_suffix(".json").write_text(json.dumps(earlier))
    args = {"init_weights": str(weights), "batch_size": 4, "lr": 3e-4, "schedule": "cosine", "seed": 1}
    state = {"model": network.state_dict(), "config": network.config.to_dict(), "args": args, "step": 900}
    record = ship(state, tmp_path / "run" / "checkpoint.pt", weights)
    assert record["training"]["steps"] == 900 and record["training"]["fine_tuned_from"] == earlier
    assert f"fine-tuned from {weights}" in record["training"]["data"]
    assert "fine_tuned_from" not in ship(state | {"args": args | {"init_weights": None}}, weights, weights)["training"]


def test_a_leg_resumed_after_shipping_over_its_starting_weights_keeps_their_record(tmp_path, shapes):
    """Train from shipped weights, ship the run over them, then resume it for more steps and ship
    again: the record keeps the weights the run started from, not the run's own first shipment."""
    from model.training.ship import main as ship_main

    weights = tmp_path / "ifnet-indoor.pt"
    save_random_network(weights, seed=3)
    started_from = {"file": weights.name, "sha256": "ab", "training": {"steps": 405}, "date": "2026-12-03"}
    weights.with_suffix(".json").write_text(json.dumps(started_from))
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    for steps in ("1", "2"):
        train_briefly(tmp_path, shapes, "--max-steps", steps, "--init-weights", str(weights))
        ship_main(["--checkpoint", str(checkpoint), "--weights", str(weights)])
        record = json.loads(weights.with_suffix(".json").read_text())
        assert record["training"]["steps"] == int(steps)
        assert record["training"]["fine_tuned_from"] == started_from, steps


def test_the_shipped_record_names_the_training_objective():
    from model.training.ship import training_objective

    paper = {"global_loss": "squared", "global_weight": 1.0, "teacher": None, "teacher_weight": 1000.0}
    assert training_objective(paper) == "the paper's three unsupervised losses"
    assert "weighted 100" in training_objective(paper | {"global_weight": 100.0})
    assert "teacher consistency with t.pt (weight 1000)" in training_objective(paper | {"teacher": "t.pt"})


def test_the_shipped_record_names_the_noise_of_the_training_pairs():
    from model.training.ship import pair_noise

    assert pair_noise({"noise": ["clean"], "jitter_sigma": 0.01}) == "clean"
    assert pair_noise({}) == "clean"  # checkpoints from before --noise trained on clean pairs
    mixed = pair_noise({"noise": ["clean", "jitter"], "jitter_sigma": 0.01})
    assert mixed == "clean, jitter mixed pair by pair, jitter sigma 0.01"


def test_only_the_full_evaluation_writes_the_published_report():
    from model.artifacts import SERVED_MODEL
    from model.training.evaluate import PUBLISHED_REPORT, QUICK_REPORT, parse_args

    assert parse_args([]).out == PUBLISHED_REPORT
    assert parse_args(["--model", os.path.relpath(SERVED_MODEL)]).out == PUBLISHED_REPORT  # the default, spelt out
    for partial in (["--limit", "100"], ["--sets", "jitter"], ["--no-baselines"], ["--shared-jitter"]):
        assert parse_args(partial).out == QUICK_REPORT, partial
    assert str(parse_args(["--limit", "5", "--out", "elsewhere"]).out) == "elsewhere"


def test_a_spread_subset_takes_the_full_runs_pairs_across_the_set():
    from model.training.evaluate import shape_indices

    assert shape_indices(908, 0, spread=True).tolist() == list(range(908))
    assert shape_indices(908, 100, spread=False).tolist() == list(range(100))
    spread = shape_indices(908, 100, spread=True)
    assert len(set(spread.tolist())) == 100 and spread[0] == 0 and spread[-1] == 907
    assert np.all(np.diff(spread) >= 9)  # no stretch of the set is left out or sampled twice
    assert shape_indices(50, 100, spread=True).tolist() == list(range(50))


def test_a_spread_subset_of_modelnet10_test_holds_every_class():
    from model.training.data import DEFAULT_DATA_DIR
    from model.training.evaluate import shape_indices

    path = DEFAULT_DATA_DIR / "modelnet10_test.npz"
    if not path.exists():
        pytest.skip(f"{path} is missing (../shared/data)")
    labels = np.load(path)["labels"]
    assert set(labels[shape_indices(len(labels), 100, spread=True)]) == set(labels)
    assert len(set(labels[shape_indices(len(labels), 100, spread=False)])) < len(set(labels))


def test_missing_data_gives_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="--data-dir"):
        load_split("train", tmp_path)


def shipped_model_errors(pairs: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic rotation (deg) and translation errors of the shipped weights on protocol pairs."""
    from model.checkpoint import load_checkpoint
    from model.geometry import registration_errors

    model = load_checkpoint(DEFAULT_WEIGHTS).model
    source = torch.from_numpy(np.stack([p["source"] for p in pairs]))
    target = torch.from_numpy(np.stack([p["target"] for p in pairs]))
    with torch.no_grad():
        out = model(source, target)
    errors = registration_errors(
        out.rotation.double().numpy(),
        out.translation.double().numpy(),
        np.stack([p["rotation"] for p in pairs]).astype(np.float64),
        np.stack([p["translation"] for p in pairs]).astype(np.float64),
    )
    return errors["rotation_deg"], errors["translation"]


@pytest.mark.slow
@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no shipped weights in the checkout")
def test_shipped_weights_register_generated_pairs():
    """Accuracy smoke test on 8 protocol pairs of synthetic shapes (needs no data).

    Tolerance: 7 of the 8 pairs within 1 degree and 0.01 (unit-sphere units), and a median
    rotation error below 0.5 degrees. Measured: 0.03-0.28 degrees and 0.0034 at worst on seven
    pairs; the seventh shape, a nearly ellipsoidal blob, is off by 61 degrees (the clean-trained
    weights: 0.08). The shipped network no longer keys on points shared exactly by both clouds,
    and misses about 2 % of clean ModelNet pairs by more than 5 degrees (docs/evaluation/). The
    shapes are not ModelNet's: this checks that the weights load and register, not the
    published accuracy.
    """
    pairs = [
        make_pair(synthetic_shape(np.random.default_rng((7, i))), Protocol(), np.random.default_rng((8, i)))
        for i in range(8)
    ]
    rotation_deg, translation = shipped_model_errors(pairs)
    registered = (rotation_deg < 1.0) & (translation < 0.01)
    assert registered.sum() >= 7, (rotation_deg, translation)
    assert np.median(rotation_deg) < 0.5, rotation_deg


@pytest.mark.slow
@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no shipped weights in the checkout")
def test_shipped_weights_register_modelnet_test_pairs():
    """8 protocol pairs of ModelNet10 test shapes (skipped without ../shared/data).

    Tolerance: every pair within 2 degrees and 0.02, median rotation error below 0.3 degrees;
    measured 0.05-0.33 degrees on seven pairs, 1.4 degrees and 0.015 on the first (a bathtub).
    """
    try:
        shapes = load_split("same")[:8]
    except FileNotFoundError as error:
        pytest.skip(str(error))
    pairs = [make_pair(shape, Protocol(), np.random.default_rng((21, i))) for i, shape in enumerate(shapes)]
    rotation_deg, translation = shipped_model_errors(pairs)
    assert rotation_deg.max() < 2.0, rotation_deg
    assert translation.max() < 0.02, translation
    assert np.median(rotation_deg) < 0.3, rotation_deg


@pytest.mark.slow
def test_fine_tuning_starts_from_the_given_weights_on_noisy_pairs(tmp_path, shapes):
    start = save_random_network(tmp_path / "start.pt", seed=123)
    train_briefly(tmp_path, shapes, "--max-steps", "1", "--lr", "1e-9", "--init-weights", str(tmp_path / "start.pt"))
    tuned = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["model"]
    for name, value in start.state_dict().items():
        if value.is_floating_point() and "running" not in name:  # batch-norm statistics move in one step
            torch.testing.assert_close(tuned[name], value, atol=1e-6, rtol=0, msg=name)


@pytest.mark.slow
def test_evaluation_reports_the_network_and_its_icp_refinement(tmp_path, shapes):
    from model.artifacts import SERVED_MODEL
    from model.training.evaluate import main as evaluate_main

    np.savez(tmp_path / "modelnet10_test.npz", points=shapes[:3])
    out = tmp_path / "eval"
    args = ["--model", str(SERVED_MODEL), "--data-dir", str(tmp_path), "--out", str(out), "--no-baselines"]
    results = evaluate_main([*args, "--sets", "same", "jitter", "--jitter-sigma", "0.002"])

    for set_name in ("same", "jitter"):
        network, refined = results[set_name]["IFNet"], results[set_name]["IFNet + ICP"]
        assert network["pairs"] == refined["pairs"] == 3
        # The refinement starts from the network's estimate and adds its own time to it.
        assert refined["ms_per_pair"] >= network["ms_per_pair"] > 0
        assert (out / f"{set_name}_rotation_errors.png").stat().st_size > 0
    # The median: the shipped network misses some of these smooth, nearly ellipsoidal blobs by tens
    # of degrees (3 of 12 shapes; one of these three), which no refinement from there recovers.
    assert results["same"]["IFNet + ICP"]["iso_r_median"] < 1.0
    report = (out / "evaluation.md").read_text()
    assert "--jitter-sigma 0.002" in report and "### jitter (3 pairs)" in report


def test_evaluation_samples_the_clouds_down_to_the_networks_point_count(tmp_path, shapes, monkeypatch):
    import dataclasses

    from model.ifnet import IFNet
    from model.training.evaluate import network_runner

    network = save_random_network(tmp_path / "big.pt", seed=5)
    small = IFNet(dataclasses.replace(network.config, num_points=256))
    torch.save({"model": network.state_dict(), "config": small.config.to_dict()}, tmp_path / "small.pt")
    seen, forward = [], IFNet.forward

    def recording_forward(self, source, target):
        seen.append((source.shape, target.shape))
        return forward(self, source, target)

    monkeypatch.setattr(IFNet, "forward", recording_forward)
    pair = make_pair(shapes[0], Protocol(), np.random.default_rng(0))
    rotation, _ = network_runner(tmp_path / "small.pt", threads=1)(pair["source"], pair["target"])
    assert seen == [((1, 256, 3), (1, 256, 3))] and rotation.shape == (3, 3)


def test_config_overrides_accept_integer_fields_only():
    from model.training.train import parse_overrides

    assert parse_overrides(["edgeconv_k=16", "attention_k=4"]) == {"edgeconv_k": 16, "attention_k": 4}
    for bad in ("edgeconv_k=1.5", "bogus=3", "edgeconv_k"):
        with pytest.raises(UserError, match="FIELD=INT"):
            parse_overrides([bad])


def test_resuming_with_another_config_is_refused_before_any_work(tmp_path, capsys):
    from model.ifnet import preset

    run = tmp_path / "run"
    run.mkdir()
    torch.save({"config": preset("fast").to_dict(), "step": 5}, run / "checkpoint.pt")
    with pytest.raises(SystemExit) as stopped:
        train_main(["--preset", "fast", "--override", "edgeconv_k=16", "--out", str(run), "--data-dir", "/nonexistent"])
    assert stopped.value.code == 2
    assert "holds a different preset or overrides; use another --out" in capsys.readouterr().err
    assert sorted(path.name for path in run.iterdir()) == ["checkpoint.pt"]  # no log started, nothing loaded


@pytest.mark.parametrize(
    ("command", "argv", "message"),
    [
        ("train", ["--batch-size", "0"], "argument --batch-size: must be more than 0, got 0"),
        ("train", ["--device", "gpu"], "--device gpu: not a torch device; use cpu or cuda"),
        ("train", ["--override", "bogus=3"], "--override 'bogus=3': expected FIELD=INT with FIELD one of"),
        ("train", ["--override", "n_iters=0"], "--override: IFNetConfig.n_iters must be at least 1, got 0"),
        ("evaluate", ["--model", "/nonexistent/model.onnx"], "--model /nonexistent/model.onnx: no such file"),
        ("evaluate", ["--threads", "-1"], "argument --threads: must be more than 0"),
        ("export", ["--weights", "{junk}"], "not a torch checkpoint or weights file torch can read"),
        ("export", ["--check-pairs", "0"], "argument --check-pairs: must be more than 0"),
        ("ship", [], "give --checkpoint"),
        ("ship", ["--checkpoint", str(DEFAULT_WEIGHTS)], "not a training checkpoint"),
        ("ship", ["--weights", "{junk}", "--evaluation", "{junk}"], "junk.json does not describe"),
    ],
)
def test_command_line_mistakes_end_in_one_line_and_status_2(tmp_path, capsys, command, argv, message):
    """Each tool names the option and the problem instead of showing a traceback."""
    import importlib

    module = {"export": "export.__main__"}.get(command, f"model.training.{command}")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(os.urandom(256))
    junk.with_suffix(".json").write_text(DEFAULT_WEIGHTS.with_suffix(".json").read_text())  # a record of other weights
    argv = [arg.format(junk=junk) for arg in argv]
    if command == "train":
        argv += ["--out", str(tmp_path / "run")]  # never the default runs/ folder
    with pytest.raises(SystemExit) as stopped:
        importlib.import_module(module).main(argv)
    assert stopped.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert message in error[-1] and "Traceback" not in "\n".join(error)
    assert not (tmp_path / "run").exists()  # refused before any work
