"""The IFNet model: interface, rotation validity, gradients, losses, and that it can learn."""

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the model tests need torch (pip install -e '.[train]')")

from model.ifnet import (  # noqa: E402
    BlockOutput,
    FeedbackRegistrationBlock,
    FeedbackTransformer,
    IFNet,
    IFNetConfig,
    preset,
)
from model.ops import fused_knn, gather_rows, knn, neighbourhood_sum, transform_points  # noqa: E402
from model.training.data import Protocol, make_pair, synthetic_shape  # noqa: E402
from model.training.losses import (  # noqa: E402
    Losses,
    global_registration_loss,
    huber,
    ifnet_losses,
    keypoints,
    neighbourhood_consistency_loss,
    pseudo_consistency_loss,
    teacher_consistency_loss,
)

# Narrow widths keep the full 3 x 3 unrolled model fast enough for unit tests.
TINY = preset("fast", emb_dims=32, attention_hidden=32, pos_hidden=16, edgeconv_widths=(16, 16, 32, 32))


def random_clouds(batch: int, n: int, seed: int = 0) -> tuple:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, n, 3, generator=g) - 0.5, torch.rand(batch, n, 3, generator=g) - 0.5


def assert_proper_rotations(rotation):
    eye = torch.eye(3).expand_as(rotation)
    assert torch.allclose(rotation @ rotation.transpose(1, 2), eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(rotation.shape[0]), atol=1e-5)


def test_gather_rows_picks_each_batch_items_own_rows():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 10, 4, generator=g)
    idx = torch.randint(0, 10, (3, 6, 2), generator=g)
    expected = torch.stack([x[b][idx[b]] for b in range(3)])  # [3, 6, 2, 4]
    assert torch.equal(gather_rows(x, idx), expected)
    assert torch.equal(gather_rows(x, idx[..., 0]), expected[:, :, 0])


def test_knn_matches_brute_force_distances_nearest_first():
    g = torch.Generator().manual_seed(3)
    query, reference = torch.rand(2, 60, 3, generator=g) + 5.0, torch.rand(2, 80, 3, generator=g) + 5.0  # off-centre
    expected_sq, expected_idx = (torch.cdist(query.double(), reference.double()) ** 2).topk(6, largest=False)
    sq_distances, idx = knn(query, reference, 6)
    assert torch.equal(idx, expected_idx)
    assert torch.allclose(sq_distances.double(), expected_sq, atol=1e-4)
    own_sq, own = knn(query, query, 6)
    assert torch.equal(own[..., 0], torch.arange(60).expand(2, 60)) and own_sq[..., 0].abs().max() < 1e-4


def test_feedback_transformer_computes_the_papers_attention():
    """softmax_k(attn_out(attn_in(f_i - f_j + pos_ij))) weighting (f_j + pos_ij), pos_ij = pos_mlp(d_i - d_j),
    over the k nearest of both clouds, written directly: the module's rewrites must not change it."""
    torch.manual_seed(4)
    attention = FeedbackTransformer(TINY)
    for norm in (m for m in attention.modules() if isinstance(m, torch.nn.BatchNorm1d)):
        norm.running_mean.normal_()
        norm.running_var.uniform_(0.5, 2.0)
    attention.eval()
    points, other = random_clouds(2, 40)
    graph = FeedbackRegistrationBlock(TINY).build_graph(points)
    descriptor, other_descriptor = torch.randn(2, 40, 14), torch.randn(2, 40, 14)
    features, other_features = torch.randn(2, 40, TINY.emb_dims), torch.randn(2, 40, TINY.emb_dims)

    idx = knn(points, torch.cat([points, other], 1), TINY.attention_k)[1]
    fused_features = torch.cat([features, other_features], 1)
    pos = attention.pos_mlp(descriptor.unsqueeze(2) - gather_rows(torch.cat([descriptor, other_descriptor], 1), idx))
    difference = features.unsqueeze(2) - gather_rows(fused_features, idx) + pos
    weights = torch.softmax(attention.attn_out(attention.attn_in(difference)), dim=2)
    expected = (weights * (gather_rows(fused_features, idx) + pos)).sum(2)

    with torch.no_grad():
        out = attention(points, graph, descriptor, features, other, other_descriptor, other_features)
    assert torch.allclose(out, expected, atol=1e-5)


def test_fused_knn_is_knn_over_both_clouds_and_survives_a_rigid_motion():
    g = torch.Generator().manual_seed(2)
    points, other = torch.rand(2, 200, 3, generator=g), torch.rand(2, 150, 3, generator=g)
    own_sq, own = knn(points, points, 12)  # the graph is built wider than the attention needs
    expected = knn(points, torch.cat([points, other], 1), 8)[1].sort(-1).values
    assert torch.equal(fused_knn(points, own, own_sq, other, 8).sort(-1).values, expected)
    # own neighbours found before a rigid motion still hold after it (the source moves every block)
    angle = torch.tensor(0.7)
    c, s = torch.cos(angle), torch.sin(angle)
    rotation = torch.stack([torch.stack([c, -s, 0 * c]), torch.stack([s, c, 0 * c]), torch.tensor([0.0, 0, 1])])
    moved = transform_points(points, rotation.expand(2, 3, 3), torch.tensor([[0.3, -0.2, 0.1]] * 2))
    expected = knn(moved, torch.cat([moved, other], 1), 8)[1].sort(-1).values
    assert torch.equal(fused_knn(moved, own, own_sq, other, 8).sort(-1).values, expected)


def test_neighbourhood_sum_equals_adjacency_products():
    g = torch.Generator().manual_seed(1)
    p = torch.rand(2, 7, 9, generator=g)
    rows_idx, cols_idx = torch.randint(0, 7, (2, 7, 3), generator=g), torch.randint(0, 9, (2, 9, 4), generator=g)

    def adjacency(idx, n):  # A[i, a] = 1 for each a in idx[i] (counted with multiplicity)
        return torch.zeros(idx.shape[0], idx.shape[1], n).scatter_add_(2, idx, torch.ones(idx.shape))

    expected = adjacency(rows_idx, 7) @ p @ adjacency(cols_idx, 9).transpose(1, 2)
    assert torch.allclose(neighbourhood_sum(p, rows_idx, cols_idx), expected, atol=1e-6)


@pytest.mark.parametrize("batch", [1, 4])
@pytest.mark.parametrize("n", [512, 768, pytest.param(1024, marks=pytest.mark.slow)])
def test_shapes_dtypes_and_proper_rotations(batch, n):
    torch.manual_seed(0)
    model = IFNet(TINY).eval()
    source, target = random_clouds(batch, n)
    with torch.no_grad():
        out = model(source, target)
    assert out.rotation.shape == (batch, 3, 3) and out.rotation.dtype == torch.float32
    assert out.translation.shape == (batch, 3) and out.translation.dtype == torch.float32
    assert len(out.blocks) == TINY.n_iters * TINY.time_steps
    assert out.blocks[0].matching.shape == (batch, n, n)
    assert out.blocks[0].weights.shape == (batch, n)
    assert_proper_rotations(out.rotation)


@pytest.mark.slow
def test_source_and_target_may_differ_in_size():
    model = IFNet(TINY).eval()
    source, _ = random_clouds(2, 600)
    _, target = random_clouds(2, 700, seed=1)
    with torch.no_grad():
        out = model(source, target)
    assert out.blocks[-1].matching.shape == (2, 600, 700)
    assert_proper_rotations(out.rotation)


def test_output_is_the_composition_of_the_last_time_step():
    """target ~ source @ R^T + t must equal applying the last time step's blocks one by one."""
    model = IFNet(TINY).eval()
    source, target = random_clouds(2, 512)
    with torch.no_grad():
        out = model(source, target)
    moved = source
    for block in out.blocks[-TINY.n_iters :]:
        moved = transform_points(moved, block.rotation, block.translation)
    assert torch.allclose(transform_points(source, out.rotation, out.translation), moved, atol=1e-5)


@pytest.mark.slow
def test_rotations_valid_for_degenerate_inputs():
    """Planar, collinear and nearly coincident clouds still give proper rotations, no NaN."""
    model = IFNet(TINY).eval()
    g = torch.Generator().manual_seed(3)
    planar = torch.rand(1, 512, 3, generator=g) * torch.tensor([1.0, 1.0, 0.0])
    line = torch.linspace(0, 1, 512).view(1, 512, 1) * torch.tensor([1.0, 2.0, 3.0]) + 1e-4 * torch.rand(1, 512, 3)
    tiny = 1e-6 * torch.rand(1, 512, 3, generator=g)
    for cloud in (planar, line, tiny):
        with torch.no_grad():
            out = model(cloud, cloud.flip(1))
        assert torch.isfinite(out.rotation).all() and torch.isfinite(out.translation).all()
        assert_proper_rotations(out.rotation)


@pytest.mark.slow
def test_gradients_reach_every_parameter():
    torch.manual_seed(0)
    model = IFNet(TINY).train()
    source, target = random_clouds(2, 512)
    losses = ifnet_losses(model(source, target), target, TINY)
    losses.total.backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not torch.any(p.grad != 0)]
    assert not missing, f"no gradient reaches {missing}"
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


def test_config_rejects_counts_and_widths_below_one():
    for field, value in (("n_iters", 0), ("time_steps", -1), ("edgeconv_k", 0), ("edgeconv_widths", (32, 0))):
        with pytest.raises(ValueError, match=f"IFNetConfig.{field} must be at least 1"):
            preset("fast", **{field: value})
    assert IFNetConfig(n_iters=1, time_steps=1).n_iters == 1


WIDTH_FIELDS = {
    "edgeconv_widths": (32, 48, 64, 128),
    "emb_dims": 96,
    "pos_hidden": 48,
    "attention_hidden": 96,
    "overlap_width": 12,
    "overlap_hidden": 24,
}


@pytest.mark.parametrize("field", WIDTH_FIELDS)
def test_every_width_is_a_config_field(field):
    """Changing any config width changes the parameter count: no layer width is a hidden literal."""
    base = IFNet(preset("fast")).num_parameters()
    assert IFNet(preset("fast", **{field: WIDTH_FIELDS[field]})).num_parameters() != base


def test_config_round_trips_and_paper_preset_has_the_paper_size():
    assert IFNet(preset("paper")).num_parameters() > 200_000  # paper sizes: ~230k parameters
    assert IFNetConfig.from_dict(preset("paper").to_dict()) == preset("paper")


# ------------------------------------------------------------------ losses


def perfect_block(rotation_error_deg: float = 0.0):
    """A hand-built block output whose pseudo target is the exact motion of the source."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    source = torch.from_numpy(synthetic_shape(rng, 512))[None]
    true_r = torch.from_numpy(Rotation.from_euler("zyx", [20, 10, 5], degrees=True).as_matrix()).float()[None]
    true_t = torch.tensor([[0.1, -0.2, 0.05]])
    target = transform_points(source, true_r, true_t)
    wrong = torch.from_numpy(Rotation.from_euler("z", rotation_error_deg, degrees=True).as_matrix()).float()[None]
    rotation = wrong @ true_r
    matching = torch.eye(512)[None] * 0.999 + 0.001 / 512  # rows peaked on the true match
    block = BlockOutput(rotation, true_t, source, target, torch.ones(1, 512), matching, torch.zeros(1, 512, 8))
    neighbours = torch.cdist(source, source).topk(5, largest=False).indices
    return block, target, neighbours


def test_losses_near_zero_for_perfect_alignment_and_larger_when_wrong():
    block, target, neighbours = perfect_block(0.0)
    bad_block, _, _ = perfect_block(30.0)
    keypoint_idx = torch.arange(256)[None]
    moved = transform_points(block.source, block.rotation, block.translation)
    bad_moved = transform_points(bad_block.source, bad_block.rotation, bad_block.translation)

    assert global_registration_loss(moved, target, 0.01).item() < 1e-8
    assert global_registration_loss(bad_moved, target, 0.01).item() > 1e-4
    assert global_registration_loss(moved, target, 0.01, on_distances=True).item() < 1e-4  # float32 rounding
    assert global_registration_loss(bad_moved, target, 0.01, on_distances=True).item() > 1.0
    assert neighbourhood_consistency_loss(block, keypoint_idx, neighbours).item() < 1e-8
    assert neighbourhood_consistency_loss(bad_block, keypoint_idx, neighbours).item() > 1.0

    sharp = pseudo_consistency_loss(block, keypoint_idx).item()
    flat = block._replace(matching=torch.full((1, 512, 512), 1.0 / 512))
    assert sharp < 0.01
    assert pseudo_consistency_loss(flat, keypoint_idx).item() > 5.0  # log(512) = 6.2


def test_the_global_loss_looks_both_ways():
    """Every source point near a target point is not enough: every target point needs a source point too."""
    target = torch.randn(1, 512, 3)
    collapsed = target[:, :1].expand(1, 512, 3)  # the whole source on one target point
    assert global_registration_loss(collapsed, target, 0.01).item() > 1e-4
    other = torch.randn(1, 512, 3)
    torch.testing.assert_close(
        global_registration_loss(other, target, 0.01), global_registration_loss(target, other, 0.01)
    )


def test_global_weight_scales_only_the_global_loss():
    losses = Losses(torch.tensor(0.5), torch.tensor(2.0), torch.tensor(3.0))
    assert losses.total.item() == 5.5  # the paper's equal weights
    assert losses.weighted(global_weight=10.0).item() == 10.0


def test_huber_is_quadratic_below_the_margin_and_linear_above_it():
    x = torch.tensor([0.0, 0.004, 0.01, 0.03, 1.0])
    margin = 0.01
    # 0.5 x^2 below the margin, margin * x - margin^2 / 2 from it on; the two meet at the margin.
    expected = torch.tensor([0.0, 0.5 * 0.004**2, 0.5 * 0.01**2, 0.01 * 0.03 - 0.5e-4, 0.01 - 0.5e-4])
    torch.testing.assert_close(huber(x, margin), expected)


def test_keypoints_are_the_highest_weighted_source_points():
    weights = torch.tensor([[0.1, 0.9, 0.5, 0.7, 0.2], [0.8, 0.1, 0.3, 0.2, 0.95]])
    block = BlockOutput(*([None] * 4), weights, None, None)
    assert keypoints(block, 2).sort(dim=1).values.tolist() == [[1, 3], [0, 4]]
    assert keypoints(block, 99).shape == (2, 5)  # never more than there are points


def test_teacher_consistency_measures_each_blocks_distance_from_the_taught_pose():
    """Two blocks, the second completing the teacher's pose: the loss is the first block's mean
    point distance from the taught positions, halved (the second contributes zero)."""
    from scipy.spatial.transform import Rotation

    from model.ifnet import IFNetOutput
    from model.ops import compose

    source = torch.rand(1, 64, 3) - 0.5
    r1 = torch.from_numpy(Rotation.from_euler("x", 20, degrees=True).as_matrix()).float()[None]
    r2 = torch.from_numpy(Rotation.from_euler("y", 10, degrees=True).as_matrix()).float()[None]
    t1, t2 = torch.tensor([[0.1, 0.0, 0.0]]), torch.tensor([[0.0, -0.2, 0.0]])
    taught_r, taught_t = compose(r1, t1, r2, t2)
    unused = dict(pseudo_target=source, weights=torch.ones(1, 64), matching=torch.eye(64)[None], target_features=source)
    first = BlockOutput(r1, t1, source, **unused)
    second = BlockOutput(r2, t2, transform_points(source, r1, t1), **unused)
    output = IFNetOutput(taught_r, taught_t, [first, second], source_graph=None)

    expected = (transform_points(source, r1, t1) - transform_points(source, taught_r, taught_t)).norm(dim=-1).mean() / 2
    assert expected.item() > 0.05
    torch.testing.assert_close(teacher_consistency_loss(output, taught_r, taught_t), expected)
    assert teacher_consistency_loss(output, r2 @ r1, t2).item() > expected.item()  # a wrong taught pose
    # Only the second block, which finishes the taught pose: nothing left to pull.
    assert teacher_consistency_loss(output, taught_r, taught_t, blocks=slice(1, None, 2)).item() < 1e-6


@pytest.mark.slow
def test_overfit_four_pairs_lowers_loss_and_registration_error():
    """50 Adam steps on 4 fixed pairs: loss falls clearly and the pairs register better."""
    from model.geometry import rotation_angle_deg

    torch.manual_seed(0)
    pairs = [
        make_pair(
            synthetic_shape(np.random.default_rng(i)),
            Protocol(num_points=512, crop_points=384),
            np.random.default_rng(i),
        )
        for i in range(4)
    ]
    batch = {k: torch.from_numpy(np.stack([p[k] for p in pairs])) for k in pairs[0]}
    model = IFNet(TINY)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def evaluate() -> float:
        model.eval()
        with torch.no_grad():
            out = model(batch["source"], batch["target"])
        model.train()
        return float(rotation_angle_deg(out.rotation.double().numpy(), batch["rotation"].double().numpy()).mean())

    error_before = evaluate()
    losses = []
    for _ in range(50):
        loss = ifnet_losses(model(batch["source"], batch["target"]), batch["target"], TINY).total
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    error_after = evaluate()
    assert np.mean(losses[-5:]) < 0.7 * np.mean(losses[:5]), losses
    assert error_after < 0.7 * error_before, (error_before, error_after)
