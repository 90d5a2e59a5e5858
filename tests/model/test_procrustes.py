"""The SVD-free weighted Procrustes solver against float64 SVD-Kabsch.

Worst errors measured on this suite's cases (64 problems each; float32 inputs, the solver works
in float64 with 20 squarings): random 2.2e-6 deg, near-180-degree 2.3e-6, planar 2.3e-6,
90 % outliers 2.3e-6, collinear-ish (spread 1e-2 around a line) 2.4e-6; what remains is the
rounding of the float32 result. The tolerances below leave headroom over those numbers.
"""

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the solver tests need torch")

from scipy.spatial.transform import Rotation  # noqa: E402

from model.geometry import rotation_angle_deg  # noqa: E402
from model.ops import rotation_from_covariance, weighted_procrustes  # noqa: E402

BATCH = 64


def kabsch_float64(source, target, weights):
    s, y, w = source.double(), target.double(), weights.double().unsqueeze(-1)
    s_mean = (w * s).sum(1, keepdim=True) / w.sum(1, keepdim=True)
    y_mean = (w * y).sum(1, keepdim=True) / w.sum(1, keepdim=True)
    h = ((s - s_mean) * w).transpose(1, 2) @ (y - y_mean)
    u, _, vt = torch.linalg.svd(h)
    v = vt.transpose(1, 2)
    d = torch.det(v @ u.transpose(1, 2))
    fix = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return v @ fix @ u.transpose(1, 2)


def rotations(seed: int, angle_deg: float | None = None) -> torch.Tensor:
    if angle_deg is None:
        return torch.tensor(Rotation.random(BATCH, random_state=seed).as_matrix(), dtype=torch.float32)
    axes = np.random.default_rng(seed).normal(size=(BATCH, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return torch.tensor(Rotation.from_rotvec(axes * np.radians(angle_deg)).as_matrix(), dtype=torch.float32)


def case(name: str):
    g = torch.Generator().manual_seed(7)
    source = torch.randn(BATCH, 400, 3, generator=g)
    weights = torch.rand(BATCH, 400, generator=g)
    rotation = rotations(1)
    if name == "near_180":
        rotation = rotations(2, angle_deg=179.99)
    elif name == "planar":
        source[..., 2] = 0.0
    elif name == "collinear_ish":
        source = torch.randn(BATCH, 400, 1, generator=g) * torch.tensor([1.0, 2.0, 0.5])
        source = source + 1e-2 * torch.randn(BATCH, 400, 3, generator=g)
    target = source @ rotation.transpose(1, 2) + torch.tensor([0.3, -1.0, 2.0])
    target = target + 1e-3 * torch.randn(target.shape, generator=g)
    if name == "outliers":
        target[:, :360] = 3.0 * torch.randn(BATCH, 360, 3, generator=g)  # 90 % outliers
    return source, target, weights


@pytest.mark.parametrize(
    ("name", "tolerance_deg"),
    [("random", 1e-4), ("near_180", 1e-4), ("planar", 1e-4), ("outliers", 1e-4), ("collinear_ish", 1e-4)],
)
def test_matches_svd_kabsch(name, tolerance_deg):
    source, target, weights = case(name)
    rotation, translation = weighted_procrustes(source, target, weights)
    reference = kabsch_float64(source, target, weights)
    worst = rotation_angle_deg(rotation.double().numpy(), reference.numpy()).max()
    assert worst < tolerance_deg, f"{name}: worst {worst:.2e} deg"
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(BATCH), atol=1e-5)


def test_translation_is_exact_for_noise_free_motion():
    g = torch.Generator().manual_seed(0)
    source = torch.randn(8, 200, 3, generator=g)
    rotation, translation = rotations(3)[:8], torch.randn(8, 3, generator=g)
    target = source @ rotation.transpose(1, 2) + translation.unsqueeze(1)
    found_r, found_t = weighted_procrustes(source, target, torch.rand(8, 200, generator=g))
    assert torch.allclose(found_r, rotation, atol=1e-4)
    assert torch.allclose(found_t, translation, atol=1e-4)


@pytest.mark.parametrize("kind", ["zero", "rank1", "rank2", "half_turn"])
def test_gradients_finite_on_degenerate_covariance(kind):
    """Where SVD's gradient is NaN (repeated or zero singular values) this solver's is finite."""
    u = torch.nn.functional.normalize(torch.tensor([[1.0, 2.0, 3.0]]), dim=-1)
    w = torch.nn.functional.normalize(torch.tensor([[-2.0, 1.0, 0.0]]), dim=-1)
    matrices = {
        "zero": torch.zeros(1, 3, 3),
        "rank1": u.transpose(0, 1) @ u,
        "rank2": u.transpose(0, 1) @ u + w.transpose(0, 1) @ w,
        "half_turn": torch.diag(torch.tensor([-1.0, -1.0, 1.0])),
    }
    h = matrices[kind].reshape(1, 3, 3).clone().requires_grad_(True)
    rotation = rotation_from_covariance(h)
    (rotation * torch.randn(1, 3, 3)).sum().backward()
    assert torch.isfinite(rotation).all()
    assert torch.isfinite(h.grad).all()
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(1), atol=1e-5)
