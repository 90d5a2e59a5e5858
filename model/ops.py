"""Torch geometry used by the network: kNN, neighbour gathering, rigid transforms, Procrustes.

Every function works on [batch, points, channels] tensors, runs on CPU and GPU and traces to
ONNX (no SVD, no eigh, no data-dependent Python control flow).
"""

import torch
from torch import Tensor

# Trace-normalised squarings of Horn's 4x4 matrix: the fewest that converge on every hard case in
# tests/model/test_procrustes.py (nearly collinear clouds have tiny eigen-gaps).
QUATERNION_SQUARINGS = 20
_TINY = 1e-12


def pairwise_sq_distances(a: Tensor, b: Tensor) -> Tensor:
    """Squared Euclidean distances [B, N, M] between rows of a [B, N, C] and b [B, M, C]."""
    inner = a @ b.transpose(1, 2)  # [B, N, M]
    sq = (a * a).sum(-1, keepdim=True) - 2.0 * inner + (b * b).sum(-1).unsqueeze(1)
    return sq.clamp_min(0.0)


def pairwise_distances(a: Tensor, b: Tensor) -> Tensor:
    """Euclidean distances [B, N, M], with a finite gradient at zero distance."""
    return torch.sqrt(pairwise_sq_distances(a, b) + _TINY)


def knn(query: Tensor, reference: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """The k reference points nearest to each query point, nearest first: (squared distances
    [B, N, k], indices [B, N, k]).

    When query is reference, position 0 is the point itself (given no duplicate points).
    """
    # Ranked by |r|^2 - 2 q.r, the squared distance less |q|^2, which is the same for every
    # candidate of a query: two fewer passes over the [B, N, M] matrix; |q|^2 is added to the k kept.
    rank_keys = (reference * reference).sum(-1).unsqueeze(1) - 2.0 * query @ reference.transpose(1, 2)
    keys, idx = rank_keys.topk(k, dim=-1, largest=False)  # [B, N, k] each
    return (keys + (query * query).sum(-1, keepdim=True)).clamp_min(0.0), idx


def fused_knn(points: Tensor, own_neighbours: Tensor, own_sq_distances: Tensor, other_points: Tensor, k: int) -> Tensor:
    """knn(points, cat([points, other_points], 1), k) indices for a cloud whose own kNN is known.

    own_neighbours [B, N, >= k] are the cloud's neighbours among its own points, self first, at
    own_sq_distances. A rigid motion leaves both unchanged, so only the other cloud is searched
    here; the k nearest of the union are the k nearest of the two candidate lists. Indices >= N
    are other_points'.
    """
    other_sq_distances, other = knn(points, other_points, k)
    candidates = torch.cat([own_neighbours[..., :k], other + points.shape[1]], dim=-1)  # [B, N, 2k]
    nearest = torch.cat([own_sq_distances[..., :k], other_sq_distances], dim=-1).topk(k, dim=-1, largest=False).indices
    return torch.gather(candidates, 2, nearest)


def gather_rows(x: Tensor, idx: Tensor) -> Tensor:
    """Rows of x [B, M, C] picked by idx [B, ...] -> [B, ..., C], e.g. idx [B, N, k] -> [B, N, k, C].

    Indexes the flattened [B * M, C] rows, which exports as one ONNX Gather of whole rows: cheaper
    in ONNX Runtime than torch.gather's GatherElements on an index expanded to every channel.
    """
    batch, m, channels = x.shape
    offset = torch.arange(batch, device=x.device).view(-1, *[1] * (idx.dim() - 1)) * m
    return x.reshape(-1, channels)[idx + offset]


def neighbour_offsets(points: Tensor, idx: Tensor) -> Tensor:
    """Each point's neighbours relative to it, neighbour - centre: [B, N, C], [B, N, k] -> [B, N, k, C]."""
    return gather_rows(points, idx) - points.unsqueeze(2)


def neighbourhood_sum(p: Tensor, rows_idx: Tensor, cols_idx: Tensor) -> Tensor:
    """S[i, j] = sum over a in rows_idx[i], b in cols_idx[j] of p[a, b]; [B, N, M].

    This is A_rows @ p @ A_cols^T for the kNN adjacency matrices, computed as row gathers of p:
    O(N * M) memory instead of the [B, N, k, M, k] tensor a direct gather would build.
    """
    rows = sum(gather_rows(p, rows_idx[..., a]) for a in range(rows_idx.shape[-1]))  # [B, N, M]
    cols = rows.transpose(1, 2).contiguous()  # [B, M, N], copied once rather than in every gather
    return sum(gather_rows(cols, cols_idx[..., b]) for b in range(cols_idx.shape[-1])).transpose(1, 2)


def transform_points(points: Tensor, rotation: Tensor, translation: Tensor) -> Tensor:
    """points [B, N, 3] -> points @ R^T + t."""
    return points @ rotation.transpose(1, 2) + translation.unsqueeze(1)


def compose(rot_a: Tensor, trans_a: Tensor, rot_b: Tensor, trans_b: Tensor) -> tuple[Tensor, Tensor]:
    """The transform that applies (rot_a, trans_a) first, then (rot_b, trans_b)."""
    rotation = rot_b @ rot_a
    translation = (rot_b @ trans_a.unsqueeze(-1)).squeeze(-1) + trans_b
    return rotation, translation


def identity_transform(batch: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Identity rotation [B, 3, 3] and zero translation [B, 3] with like's dtype and device."""
    eye = torch.eye(3, dtype=like.dtype, device=like.device)
    return eye.expand(batch, 3, 3), like.new_zeros(batch, 3)


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternions [B, 4] (w, x, y, z) -> rotation matrices [B, 3, 3]."""
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, -1).view(-1, 3, 3)


def rotation_from_covariance(h: Tensor) -> Tensor:
    """The rotation R maximising trace(R H) for H = sum a b^T [B, 3, 3] (a to b), without SVD.

    Horn's method: the best rotation is the quaternion that is the top eigenvector of a
    symmetric 4x4 matrix built from H. Shifting that matrix by sqrt(3) * ||H||_F makes every
    eigenvalue non-negative, so repeated squaring (trace-normalised to stay finite) converges to
    a projector onto the top eigenvector. The result is always a proper rotation.
    """
    sxx, sxy, sxz, syx, syy, syz, szx, szy, szz = h.reshape(-1, 9).unbind(-1)
    n = torch.stack(
        [
            sxx + syy + szz,
            syz - szy,
            szx - sxz,
            sxy - syx,
            syz - szy,
            sxx - syy - szz,
            sxy + syx,
            szx + sxz,
            szx - sxz,
            sxy + syx,
            syy - sxx - szz,
            syz + szy,
            sxy - syx,
            szx + sxz,
            syz + szy,
            szz - sxx - syy,
        ],
        -1,
    ).view(-1, 4, 4)
    shift = 3.0**0.5 * torch.sqrt((h * h).sum((-2, -1)) + _TINY) + 1e-6  # [B]
    eye4 = torch.eye(4, dtype=h.dtype, device=h.device)
    a = n + shift.view(-1, 1, 1) * eye4
    # Diagonals as (a * I).sum(-1): torch.diagonal exports as an ONNX If node whose declared
    # type is float32 even in this float64 code.
    for _ in range(QUATERNION_SQUARINGS):
        a = a @ a
        a = a / ((a * eye4).sum((-2, -1)).view(-1, 1, 1) + _TINY)
    # Every column of the converged projector is parallel to the eigenvector; the one with the
    # largest diagonal entry is the best conditioned. One more multiply sharpens it.
    best = (a * eye4).sum(-1).argmax(-1)  # [B]
    column = torch.gather(a, 2, best.view(-1, 1, 1).expand(-1, 4, 1))  # [B, 4, 1]
    q = (a @ column).squeeze(-1)
    q = q / torch.sqrt((q * q).sum(-1, keepdim=True) + _TINY)
    return quaternion_to_matrix(q)


def weighted_procrustes(source: Tensor, target: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Rigid (R [B, 3, 3], t [B, 3]) minimising sum w_i |R s_i + t - y_i|^2.

    source, target [B, N, 3], weights [B, N] (non-negative, not necessarily normalised).
    """
    # float64 for the 3x3 problem: near-degenerate clouds (e.g. almost collinear) keep their
    # rotation information in covariance entries far below float32 resolution of the large ones.
    dtype = source.dtype
    source, target, weights = source.double(), target.double(), weights.double()
    w = weights.unsqueeze(-1)  # [B, N, 1]
    total = w.sum(1, keepdim=True) + _TINY
    src_mean = (w * source).sum(1, keepdim=True) / total  # [B, 1, 3]
    tgt_mean = (w * target).sum(1, keepdim=True) / total
    h = ((source - src_mean) * w).transpose(1, 2) @ (target - tgt_mean)  # [B, 3, 3]
    rotation = rotation_from_covariance(h)
    translation = tgt_mean.squeeze(1) - (rotation @ src_mean.transpose(1, 2)).squeeze(-1)
    return rotation.to(dtype), translation.to(dtype)
