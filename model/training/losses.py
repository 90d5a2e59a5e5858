"""The paper's three unsupervised losses; no ground-truth pose is used.

Each is computed for every Feedback Registration Block and averaged with equal weight.
"""

from typing import NamedTuple

import torch
from torch import Tensor

from model.ifnet import BlockOutput, IFNetConfig, IFNetOutput
from model.ops import gather_rows, pairwise_sq_distances, transform_points


class Losses(NamedTuple):
    global_registration: Tensor
    neighbourhood_consistency: Tensor
    pseudo_consistency: Tensor

    @property
    def total(self) -> Tensor:
        """The paper's objective: the three losses with equal weights."""
        return self.weighted(global_weight=1.0)

    def weighted(self, global_weight: float) -> Tensor:
        """The objective with the global registration loss scaled (an experiment knob)."""
        return global_weight * self.global_registration + self.neighbourhood_consistency + self.pseudo_consistency


def huber(x: Tensor, margin: float) -> Tensor:
    """Huber function on (already squared) distances, as the official code applies it."""
    return torch.where(x < margin, 0.5 * x * x, margin * x - 0.5 * margin * margin)


def global_registration_loss(moved_source: Tensor, target: Tensor, margin: float, on_distances: bool = False) -> Tensor:
    """Huber of the bidirectional nearest-neighbour distances, summed over points; [B].

    As the official code does it, the Huber is of squared distances: ~0.5 d^4 near the optimum,
    whose gradient vanishes where noisy pairs still need one. on_distances (an experiment) takes
    it of the distances instead, with margin sqrt(margin): ~0.5 d^2, gradient ~d.
    """
    sq = pairwise_sq_distances(moved_source, target)  # [B, N, M]
    nearest = torch.cat([sq.amin(dim=2), sq.amin(dim=1)], dim=1)  # [B, N + M]
    if on_distances:
        return huber(torch.sqrt(nearest + 1e-12), margin**0.5).sum(-1)
    return huber(nearest, margin).sum(-1)


def keypoints(block: BlockOutput, count: int) -> Tensor:
    """Indices [B, K] of the source points with the highest overlap weights."""
    return block.weights.topk(min(count, block.weights.shape[1]), dim=1).indices


def neighbourhood_consistency_loss(block: BlockOutput, keypoint_idx: Tensor, neighbour_idx: Tensor) -> Tensor:
    """Keypoints and their kNN edges, moved by the block's transform, against the pseudo target's; [B].

    As in the official code: squared keypoint residuals plus squared edge residuals / k.
    """
    rotation, translation = block.rotation, block.translation
    src_kp = gather_rows(block.source, keypoint_idx)  # [B, K, 3]
    tgt_kp = gather_rows(block.pseudo_target, keypoint_idx)
    point_term = (transform_points(src_kp, rotation, translation) - tgt_kp).pow(2).sum((1, 2))

    kp_neighbours = gather_rows(neighbour_idx, keypoint_idx)  # [B, K, k]
    src_edges = src_kp.unsqueeze(2) - gather_rows(block.source, kp_neighbours)  # [B, K, k, 3]
    tgt_edges = tgt_kp.unsqueeze(2) - gather_rows(block.pseudo_target, kp_neighbours)
    src_edges = src_edges @ rotation.unsqueeze(1).transpose(-1, -2)
    edge_term = (src_edges - tgt_edges).pow(2).sum((1, 2, 3)) / neighbour_idx.shape[-1]
    return point_term + edge_term


def pseudo_consistency_loss(block: BlockOutput, keypoint_idx: Tensor) -> Tensor:
    """Cross-entropy of each keypoint's matching row against its own argmax; [B]."""
    rows = gather_rows(block.matching, keypoint_idx)  # [B, K, M]
    return -torch.log(rows.amax(dim=-1) + 1e-15).mean(-1)


def teacher_consistency_loss(
    output: IFNetOutput,
    rotation: Tensor,
    translation: Tensor,
    blocks: slice = slice(None),
    taught: Tensor | None = None,
) -> Tensor:
    """Mean distance between the source as each block leaves it and as a teacher's (R, t) moves it.

    The teacher's (R, t) [B, 3, 3], [B, 3] is a trained network's estimate on the pair before its
    noise, not the true pose: a registration signal on noisy pairs, whose clouds share no exact
    points for the paper's losses to lock onto. Averaged over the chosen blocks (all by default;
    `slice(n_iters - 1, None, n_iters)` takes each time step's finished estimate), points and the
    pairs the teacher answered (`taught` [B], 1 or 0; default: all).
    """
    goal = transform_points(output.blocks[0].source, rotation, translation)  # [B, N, 3]
    distances = torch.stack(
        [
            (transform_points(block.source, block.rotation, block.translation) - goal).norm(dim=-1).mean(dim=-1)
            for block in output.blocks[blocks]
        ]
    )  # [blocks, B]
    if taught is None:
        return distances.mean()
    return (distances * taught).sum() / (distances.shape[0] * taught.sum().clamp(min=1.0))


def ifnet_losses(output: IFNetOutput, target: Tensor, config: IFNetConfig, global_on_distances: bool = False) -> Losses:
    """The three losses averaged over blocks and batch (global_on_distances: see global_registration_loss)."""
    terms = torch.zeros(3, device=target.device)
    for block in output.blocks:
        moved = transform_points(block.source, block.rotation, block.translation)
        idx = keypoints(block, config.n_keypoints)
        terms = terms + torch.stack(
            [
                global_registration_loss(moved, target, config.huber_margin, global_on_distances).mean(),
                neighbourhood_consistency_loss(block, idx, output.source_graph.edgeconv).mean(),
                pseudo_consistency_loss(block, idx).mean(),
            ]
        )
    return Losses(*(terms / len(output.blocks)))
