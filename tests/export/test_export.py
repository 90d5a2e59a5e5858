"""Contract tests: the ONNX graph computes what the torch model computes, on the same weights.

Tolerances (also in the README):
  * one Feedback Registration Block, same inputs: rotation entries within 1e-3, translation 1e-4;
  * a 1-iteration, 1-time-step random-weights model end to end: rotation and translation 1e-3;
  * the shipped weights end to end: rotation entries within 1e-3 and the rotation error against
    the known motion within 0.01 degrees of torch's.
A 9-block random-weights model is not compared end to end: random blocks amplify float32 noise
so much that torch float32 and torch float64 already disagree by degrees.

Inputs are continuous random or ModelNet shapes without duplicate points. Exact distance ties
(duplicates, grid data) would break parity for a reason unrelated to the export: ONNX Runtime's
TopK puts the lower index first, torch's order among equal distances is unspecified, so the two
pick different neighbours.
"""

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the export tests need torch")
pytest.importorskip("onnx", reason="the export tests need onnx")

from export.onnx_export import (  # noqa: E402
    DYNAMIC_AXES,
    ParityReport,
    RegistrationGraph,
    compare_with_torch,
    export_onnx,
    fold_batch_norms,
)
from model.artifacts import DEFAULT_WEIGHTS, SERVED_MODEL, file_sha256, ort_session  # noqa: E402
from model.checkpoint import load_checkpoint  # noqa: E402
from model.ifnet import ChannelBatchNorm, IFNet, IFNetConfig, preset  # noqa: E402
from model.training.data import evaluation_pairs  # noqa: E402

SHIPPED = DEFAULT_WEIGHTS.exists() and SERVED_MODEL.exists()


class SingleBlock(torch.nn.Module):
    """One FRB as a graph: (moved source, target[, fed-back target features]) -> (R, t)."""

    def __init__(self, model: IFNet, with_feedback: bool):
        super().__init__()
        self.block = fold_batch_norms(model).block  # as RegistrationGraph exports it
        self.with_feedback = with_feedback

    def forward(self, source, target, feedback=None):
        context = self.block.encode_target(target)
        out = self.block(source, self.block.build_graph(source), context, feedback if self.with_feedback else None)
        return out.rotation, out.translation


def block_inputs(model: IFNet, source, target) -> list[tuple]:
    """The inputs each of the model's 9 blocks saw in a torch run: (moved source, feedback)."""
    with torch.no_grad():
        out = model(source, target)
    n_iters = model.config.n_iters
    inputs = []
    for index, block in enumerate(out.blocks):
        feedback = None if index < n_iters else out.blocks[index - n_iters].target_features
        inputs.append((block.source, feedback, block.rotation, block.translation))
    return inputs


def export_block(model: IFNet, with_feedback: bool, path: Path, n: int):
    example = [torch.rand(1, n, 3) - 0.5, torch.rand(1, n, 3) - 0.5]
    names = ["source", "target"]
    axes = {"source": DYNAMIC_AXES["source"], "target": DYNAMIC_AXES["target"]}
    if with_feedback:
        example.append(torch.randn(1, n, model.config.emb_dims))
        names.append("feedback")
        axes["feedback"] = {0: "batch", 1: "n_target"}
    export_onnx(SingleBlock(model, with_feedback), path, tuple(example), names, ["rotation", "translation"], axes)
    return ort_session(path)


def stacked_pairs(batch: int) -> tuple:
    pairs = evaluation_pairs(batch, seed=5)
    return (
        torch.from_numpy(np.stack([p["source"] for p in pairs])),
        torch.from_numpy(np.stack([p["target"] for p in pairs])),
    )


@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no shipped weights in the checkout")
@pytest.mark.parametrize("batch", [1, pytest.param(4, marks=pytest.mark.slow)])
def test_each_block_matches_torch_on_the_same_inputs(tmp_path, batch):
    """On the shipped weights: with random weights one block's float32 noise alone reaches ~1e-3."""
    model = load_checkpoint(DEFAULT_WEIGHTS).model
    source, target = stacked_pairs(batch)
    first = export_block(model, False, tmp_path / "block_t0.onnx", source.shape[1])
    later = export_block(model, True, tmp_path / "block_fb.onnx", source.shape[1])
    for index, (moved, feedback, rotation, translation) in enumerate(block_inputs(model, source, target)):
        feeds = {"source": moved.numpy(), "target": target.numpy()}
        session = first if feedback is None else later
        if feedback is not None:
            feeds["feedback"] = feedback.numpy()
        rot_ort, trans_ort = session.run(None, feeds)
        assert np.abs(rot_ort - rotation.numpy()).max() <= 1e-3, f"block {index}"
        assert np.abs(trans_ort - translation.numpy()).max() <= 1e-4, f"block {index}"


def test_folding_batch_norms_keeps_the_evaluation_model():
    torch.manual_seed(3)
    model = IFNet(preset("fast", n_iters=1, time_steps=1))
    for norm in (m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d)):
        # statistics and affine parameters far from the initial identity, so a wrong fold shows
        norm.running_mean.uniform_(-1, 1)
        norm.running_var.uniform_(0.5, 2)
        norm.weight.data.uniform_(-2, 2)  # negative scales too: the folded EdgeConv pools before its bias
        norm.bias.data.uniform_(-1, 1)
    model.eval()
    folded = fold_batch_norms(model)
    # The overlap predictor's norms follow convolutions, which ONNX Runtime fuses itself.
    assert not any(isinstance(m, ChannelBatchNorm) for m in folded.modules())
    assert any(isinstance(m, ChannelBatchNorm) for m in model.modules()), "the original was changed"
    source, target = stacked_pairs(2)
    with torch.no_grad():
        expected, actual = model(source, target).blocks[0], folded(source, target).blocks[0]
    # Rotations are left out: with random weights the Procrustes step turns float noise into
    # large differences; the shipped weights' per-block test checks them on the folded graph.
    for name in ("target_features", "matching", "pseudo_target", "weights"):
        torch.testing.assert_close(getattr(actual, name), getattr(expected, name), atol=1e-4, rtol=1e-4, msg=name)


def test_one_iteration_one_step_random_model_end_to_end(tmp_path):
    torch.manual_seed(1)
    model = IFNet(preset("fast", n_iters=1, time_steps=1)).eval()
    source, target = stacked_pairs(4)
    path = tmp_path / "one_block.onnx"
    export_onnx(
        RegistrationGraph(model),
        path,
        (source[:1], target[:1]),
        ["source", "target"],
        ["rotation", "translation"],
        DYNAMIC_AXES,
    )
    rot_ort, trans_ort = ort_session(path).run(None, {"source": source.numpy(), "target": target.numpy()})
    with torch.no_grad():
        out = model(source, target)
    assert np.abs(rot_ort - out.rotation.numpy()).max() <= 1e-3
    assert np.abs(trans_ort - out.translation.numpy()).max() <= 1e-3


def test_dynamic_batch_and_point_counts(tmp_path):
    """Batch and both point counts are dynamic: other sizes than the export example run, as in torch."""
    torch.manual_seed(2)
    model = IFNet(preset("fast", n_iters=1, time_steps=2)).eval()
    path = tmp_path / "dynamic.onnx"
    export_onnx(
        RegistrationGraph(model),
        path,
        (torch.rand(1, 64, 3), torch.rand(1, 64, 3)),
        ["source", "target"],
        ["rotation", "translation"],
        DYNAMIC_AXES,
    )
    rng = np.random.default_rng(2)
    source, target = rng.random((3, 300, 3), dtype=np.float32), rng.random((3, 420, 3), dtype=np.float32)
    rotation, translation = ort_session(path).run(None, {"source": source, "target": target})
    assert rotation.shape == (3, 3, 3) and translation.shape == (3, 3)
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-5)
    with torch.no_grad():  # and at those sizes the graph still computes what torch does
        out = model(torch.from_numpy(source), torch.from_numpy(target))
    assert np.abs(rotation - out.rotation.numpy()).max() <= 1e-3
    assert np.abs(translation - out.translation.numpy()).max() <= 1e-3


@pytest.mark.slow
@pytest.mark.skipif(not SHIPPED, reason="no shipped weights and ONNX model in the checkout")
def test_committed_onnx_matches_committed_weights():
    """Outputs, not bytes: the committed ONNX must compute what the committed weights compute."""
    session = ort_session(SERVED_MODEL)
    declared = {value.name: value.shape for value in (*session.get_inputs(), *session.get_outputs())}
    assert declared["source"] == ["batch", "n_source", 3] and declared["target"] == ["batch", "n_target", 3]
    assert declared["rotation"] == ["batch", 3, 3] and declared["translation"][0] == "batch"  # README's contract
    metadata = session.get_modelmeta().custom_metadata_map
    assert metadata["weights_sha256"] == file_sha256(DEFAULT_WEIGHTS), "ONNX exported from other weights"
    record = json.loads(DEFAULT_WEIGHTS.with_suffix(".json").read_text())
    assert record["sha256"] == file_sha256(DEFAULT_WEIGHTS)
    model = load_checkpoint(DEFAULT_WEIGHTS).model
    assert IFNetConfig.from_dict(json.loads(metadata["config"])) == model.config
    assert int(metadata["num_points"]) == model.config.num_points
    # The recorded minimum is the graph's: it runs at that many points per cloud and not below.
    fewest = int(metadata["min_points"])
    assert fewest == model.config.graph_k
    clouds = np.random.default_rng(0).random((2, 1, fewest, 3), dtype=np.float32)
    session.run(None, {"source": clouds[0], "target": clouds[1]})
    with pytest.raises(Exception, match="TopK"):
        session.run(None, {"source": clouds[0, :, 1:], "target": clouds[1, :, 1:]})

    report = compare_with_torch(session, model, evaluation_pairs(6, seed=11))
    assert report.max_rotation_entry <= 1e-3, report
    assert report.max_translation_entry <= 1e-3, report
    assert report.max_angle_difference_deg <= 0.01, report


@pytest.mark.slow
@pytest.mark.parametrize("draft", sorted((SERVED_MODEL.parent / "drafts").glob("*.onnx")), ids=lambda path: path.stem)
def test_each_committed_draft_is_its_models_weights_over_one_block(draft):
    """A draft (service/models/drafts/NAME.onnx) runs the weights of the model NAME.onnx, one block
    on 384 points per cloud, and computes what those weights compute over that unroll."""
    draft_metadata = ort_session(draft).get_modelmeta().custom_metadata_map
    model_metadata = ort_session(SERVED_MODEL.parent / draft.name).get_modelmeta().custom_metadata_map
    assert draft_metadata["weights_sha256"] == model_metadata["weights_sha256"]
    config = json.loads(draft_metadata["config"])
    assert (config["time_steps"], config["n_iters"], config["num_points"]) == (1, 1, 384)
    weights = next(
        path for path in DEFAULT_WEIGHTS.parent.glob("*.pt") if file_sha256(path) == draft_metadata["weights_sha256"]
    )
    model = load_checkpoint(weights, iterations=1, time_steps=1).model
    report = compare_with_torch(ort_session(draft), model, evaluation_pairs(4, seed=11))
    assert report.passes(1e-3, 1e-3, 0.01), report


@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no shipped weights in the checkout")
def test_more_iterations_run_the_same_block_longer():
    """The override changes only how often the shared block runs: the first time step's first
    three blocks see the same inputs, so they give what the trained 3-iteration model gives."""
    trained = load_checkpoint(DEFAULT_WEIGHTS).model
    longer = load_checkpoint(DEFAULT_WEIGHTS, iterations=5).model
    assert longer.config.n_iters == 5 and longer.config.time_steps == trained.config.time_steps
    source, target = stacked_pairs(1)
    with torch.no_grad():
        short_out, long_out = trained(source, target), longer(source, target)
    assert len(long_out.blocks) == 5 * trained.config.time_steps
    for index in range(trained.config.n_iters):
        torch.testing.assert_close(long_out.blocks[index].rotation, short_out.blocks[index].rotation)
    with pytest.raises(ValueError, match="at least 1"):
        load_checkpoint(DEFAULT_WEIGHTS, iterations=0)


@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no shipped weights in the checkout")
def test_export_command_records_the_unroll(tmp_path):
    from export.__main__ import main, parse_args

    output = tmp_path / "ifnet-2.onnx"
    argv = ["--iterations", "2", "--time-steps", "1", "--points", "384", "--output", str(output), "--check-pairs", "2"]
    assert main(argv) == 0
    metadata = ort_session(output).get_modelmeta().custom_metadata_map
    config = json.loads(metadata["config"])
    assert (config["n_iters"], config["time_steps"], config["num_points"]) == (2, 1, 384)
    assert metadata["weights_sha256"] == file_sha256(DEFAULT_WEIGHTS)
    assert metadata["preset"] == torch.load(DEFAULT_WEIGHTS, weights_only=True)["preset"]
    exported = IFNetConfig.from_dict(config)
    assert (metadata["num_points"], metadata["min_points"]) == (str(exported.num_points), str(exported.graph_k))
    for option in ("--iterations", "--time-steps", "--points"):
        with pytest.raises(SystemExit):
            parse_args([option, "0"])


@pytest.mark.parametrize(
    ("entries", "expected"),
    [({"preset": "fast"}, "fast"), ({"args": {"preset": "small"}}, "small"), ({}, "custom")],
    ids=["shipped weights", "checkpoint keeping it among its arguments", "neither"],
)
def test_a_weights_file_is_loaded_with_its_preset(tmp_path, entries, expected):
    model = IFNet(preset("fast", n_iters=1, time_steps=1))
    path = tmp_path / "weights.pt"
    torch.save({"model": model.state_dict(), "config": model.config.to_dict(), **entries}, path)
    loaded = load_checkpoint(path)
    assert (loaded.preset, loaded.sha256) == (expected, file_sha256(path))
    assert loaded.model.config == model.config and not loaded.model.training


def test_parity_fails_on_any_of_its_three_measures():
    report = ParityReport(max_rotation_entry=1e-4, max_translation_entry=1e-4, max_angle_difference_deg=1e-3, pairs=2)
    assert report.passes(rotation_tol=1e-3, translation_tol=1e-3, angle_tol_deg=0.01)
    assert not report.passes(rotation_tol=1e-5, translation_tol=1e-3, angle_tol_deg=0.01)
    assert not report.passes(rotation_tol=1e-3, translation_tol=1e-5, angle_tol_deg=0.01)
    assert not report.passes(rotation_tol=1e-3, translation_tol=1e-3, angle_tol_deg=1e-4)


@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no shipped weights in the checkout")
def test_export_command_refuses_to_write_a_file_that_disagrees_with_torch(tmp_path, capsys):
    from export.__main__ import main

    output = tmp_path / "ifnet.onnx"
    # A negative tolerance no difference can meet stands in for an export that disagrees.
    argv = ["--iterations", "1", "--time-steps", "1", "--output", str(output), "--check-pairs", "1"]
    assert main([*argv, "--translation-tol", "-1"]) == 1
    assert not output.exists()
    assert "refusing to write" in capsys.readouterr().err
