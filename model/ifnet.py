"""IFNet: Iterative Feedback Network for unsupervised point cloud registration (Xie et al. 2024).

Points are [batch, num_points, 3]. `IFNet(config)(source, target)` returns the rotation R and
translation t with target ~ source @ R^T + t, plus every block's intermediate results for the
unsupervised losses in `model.training.losses`.

Structure (paper, Method section): one Feedback Registration Block (FRB) whose weights are
shared is unrolled over `time_steps` x `n_iters`. Each time step registers the original source
from scratch in `n_iters` blocks, moving the source after each block; block n at time step s
receives the target's high-level features that block n produced at time step s - 1.
"""

from dataclasses import asdict, dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from model.ops import (
    compose,
    fused_knn,
    gather_rows,
    identity_transform,
    knn,
    neighbour_offsets,
    neighbourhood_sum,
    pairwise_distances,
    transform_points,
    weighted_procrustes,
)


@dataclass(frozen=True)
class IFNetConfig:
    edgeconv_k: int = 5  # k1: neighbours of the EdgeConv graph (self included)
    edgeconv_widths: tuple[int, ...] = (32, 32, 64, 128)
    emb_dims: int = 256  # width of the point features
    score_k: int = 5  # k2: neighbourhood-score kNN (self included, then dropped)
    attention_k: int = 16  # neighbours each point attends over in the Feedback Transformer
    pos_hidden: int = 64  # hidden width of the positional MLP on the geometry-aware descriptor
    attention_hidden: int = 256  # hidden width of the attention MLP
    overlap_width: int = 8  # first width of the overlap predictor (the official code's `dim`)
    overlap_hidden: int = 16
    n_iters: int = 3
    time_steps: int = 3
    n_keypoints: int = 256  # top-weighted points used by two of the losses
    nn_margin: float = 0.7  # alpha in exp(alpha - S) * D
    huber_margin: float = 0.01  # margin of the global registration loss
    num_points: int = 768  # native point count the model is trained and served at

    def __post_init__(self) -> None:
        # A zero count or width builds a graph that fails far from here (or silently does nothing).
        for name, value in asdict(self).items():
            sizes = value if isinstance(value, (tuple, list)) else (value,)
            if isinstance(sizes[0], int) and min(sizes) < 1:
                raise ValueError(f"IFNetConfig.{name} must be at least 1, got {value}")

    @property
    def graph_k(self) -> int:
        """Width of each cloud's kNN graph, so also the fewest points per cloud the model runs on."""
        return max(self.edgeconv_k, self.attention_k, self.score_k, 3)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "IFNetConfig":
        values = dict(values)
        values["edgeconv_widths"] = tuple(values["edgeconv_widths"])
        return cls(**values)


PRESETS: dict[str, IFNetConfig] = {
    # The paper's sizes and the official code's hyper-parameters.
    "paper": IFNetConfig(),
    # Smaller widths and attention neighbourhoods for CPU serving; timings in the README's preset table.
    "small": IFNetConfig(emb_dims=128, attention_hidden=128, attention_k=8),
    "fast": IFNetConfig(emb_dims=64, attention_hidden=64, attention_k=8, pos_hidden=32),
}


def preset(name: str, **overrides) -> IFNetConfig:
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)


class PointMLP(nn.Sequential):
    """Per-point (1x1) layers on [..., C] tensors: Linear, BatchNorm, activation."""

    def __init__(self, widths: list[int], final_activation: bool = True, bias: bool = False):
        layers: list[nn.Module] = []
        for i, (c_in, c_out) in enumerate(zip(widths[:-1], widths[1:], strict=True)):
            last = i == len(widths) - 2
            layers.append(nn.Linear(c_in, c_out, bias=bias or (last and not final_activation)))
            if not last or final_activation:
                layers += [ChannelBatchNorm(c_out), nn.ReLU()]
        super().__init__(*layers)


class ChannelBatchNorm(nn.BatchNorm1d):
    """BatchNorm over the last (channel) axis of a [..., C] tensor."""

    def forward(self, x: Tensor) -> Tensor:
        return super().forward(x.reshape(-1, x.shape[-1])).view(x.shape)


class EdgeConv(nn.Module):
    """DGCNN-lite point features from the kNN graph (feature extraction)."""

    def __init__(self, config: IFNetConfig):
        super().__init__()
        widths = (3, *config.edgeconv_widths)
        self.layers = nn.ModuleList(PointMLP([a, b]) for a, b in zip(widths[:-1], widths[1:], strict=True))
        self.project = PointMLP([sum(config.edgeconv_widths), config.emb_dims])

    def forward(self, points: Tensor, neighbour_idx: Tensor) -> Tensor:
        # points [B, N, 3], neighbour_idx [B, N, k] -> features [B, N, emb_dims]
        x = neighbour_offsets(points, neighbour_idx)  # [B, N, k, 3]
        pooled = []
        for layer in self.layers[:-1]:
            x = layer(x)
            pooled.append(x.amax(dim=2))  # [B, N, C_layer]
        pooled.append(max_pooled(self.layers[-1], x))  # the last layer's output is only pooled
        return self.project(torch.cat(pooled, dim=-1))


def max_pooled(layer: PointMLP, x: Tensor) -> Tensor:
    """layer(x).amax(dim=2) for a one-layer PointMLP (Linear, norm, ReLU) on x [B, N, k, C].

    The ReLU and, once the norm is folded into the linear layer (export), its per-channel bias are
    monotone, so they commute with the max over the neighbours and run on the pooled [B, N, C']
    rather than on [B, N, k, C'].
    """
    linear, norm, relu = layer
    if isinstance(norm, nn.Identity):  # folded by export.onnx_export.fold_batch_norms
        return relu(F.linear(x, linear.weight).amax(dim=2) + linear.bias)
    return relu(norm(linear(x)).amax(dim=2))


def geometry_descriptor(points: Tensor, nearest_two: Tensor) -> Tensor:
    """The 14-d geometry-aware descriptor [p, e1, e2, |e1|, |e2|, e1 x e2]; [B, N, 14].

    nearest_two [B, N, 2] are each point's two nearest other points.
    """
    edge1, edge2 = neighbour_offsets(points, nearest_two).unbind(2)  # [B, N, 3] each
    lengths = torch.stack([edge1.norm(dim=-1), edge2.norm(dim=-1)], dim=-1)
    normal = torch.cross(edge1, edge2, dim=-1)
    return torch.cat([points, edge1, edge2, lengths, normal], dim=-1)


def softmax_weighted_sum(logits: Tensor, values: Tensor, dim: int) -> Tensor:
    """sum(softmax(logits, dim) * values, dim), with the softmax written out.

    ONNX Runtime's Softmax on an axis other than the last transposes its input there and back,
    which costs more than these five operators over the few neighbours of a [B, N, k, C] tensor.
    """
    scores = torch.exp(logits - logits.amax(dim=dim, keepdim=True))
    return (scores * values).sum(dim=dim) / scores.sum(dim=dim)


class FeedbackTransformer(nn.Module):
    """Point features refined by attention over kNN of the fused [own cloud, other cloud] set.

    For the source at time step s the other cloud's features are the target's high-level
    features fed back from time step s - 1 (paper Eq. 3-5); the positional embedding is an MLP
    of the descriptor difference.
    """

    def __init__(self, config: IFNetConfig):
        super().__init__()
        c = config.emb_dims
        self.k = config.attention_k
        self.pos_mlp = PointMLP([14, config.pos_hidden, c], final_activation=False, bias=True)
        # attn_in is linear, so on (f_i - f_j + pos) it splits into per-point terms computed
        # before the neighbour gather (exact, and k times cheaper) plus a per-neighbour pos term,
        # which goes through attn_in and pos_mlp's last (linear) layer as one product of the two.
        self.attn_in = nn.Linear(c, config.attention_hidden)
        self.attn_out = nn.Sequential(
            ChannelBatchNorm(config.attention_hidden),
            nn.ReLU(),
            nn.Linear(config.attention_hidden, c),
        )

    def forward(
        self,
        points: Tensor,
        graph: "CloudGraph",
        descriptor: Tensor,
        features: Tensor,
        other_points: Tensor,
        other_descriptor: Tensor,
        other_features: Tensor,
    ) -> Tensor:
        # points [B, N, 3] with their graph, descriptor [B, N, 14], features [B, N, C]; other_* over M points
        idx = fused_knn(points, graph.attention, graph.attention_sq_distances, other_points, self.k)  # [B, N, k]
        fused_descriptor = torch.cat([descriptor, other_descriptor], dim=1)
        fused_features = torch.cat([features, other_features], dim=1)  # [B, N+M, C]

        *hidden_layers, pos_out = self.pos_mlp  # pos_out is linear
        hidden = descriptor.unsqueeze(2) - gather_rows(fused_descriptor, idx)  # [B, N, k, 14]
        for layer in hidden_layers:
            hidden = layer(hidden)  # -> [B, N, k, P]
        # pos = W_p hidden + b_p and attn_in(pos) = (W_a W_p) hidden + attn_in(b_p): one layer
        # instead of two on the [B, N, k, .] rows, and every bias added to per-point rows before
        # the gather rather than to the k times larger neighbour rows after it.
        values = gather_rows(fused_features + pos_out.bias, idx) + F.linear(hidden, pos_out.weight)  # [B, N, k, C]
        projected = F.linear(fused_features, self.attn_in.weight)  # [B, N+M, H], no bias
        query = projected[:, : points.shape[1]] + self.attn_in(pos_out.bias)  # [B, N, H]
        pos_logits = F.linear(hidden, self.attn_in.weight @ pos_out.weight)  # attn_in(pos) less its bias
        logits = self.attn_out(query.unsqueeze(2) - gather_rows(projected, idx) + pos_logits)
        return softmax_weighted_sum(logits, values, dim=2)  # over the k neighbours, per channel: [B, N, C]


class MatchingMatrix(nn.Module):
    """Soft correspondences [B, N, M] from feature distances sharpened by neighbourhood agreement."""

    def __init__(self, config: IFNetConfig):
        super().__init__()
        self.alpha = config.nn_margin

    def forward(
        self, src_features: Tensor, tgt_features: Tensor, src_neighbours: Tensor, tgt_neighbours: Tensor
    ) -> Tensor:
        # *_neighbours [B, N, k2 - 1]: kNN indices without the point itself
        neg_distance = -pairwise_distances(src_features, tgt_features)  # -D, [B, N, M]
        preliminary = torch.softmax(neg_distance, dim=-1)  # M_P
        score = neighbourhood_sum(preliminary, src_neighbours, tgt_neighbours)
        score = score / src_neighbours.shape[-1]  # M_S, normalised as the official code does
        return torch.softmax(torch.exp(self.alpha - score) * neg_distance, dim=-1)


class OverlapPredictor(nn.Module):
    """Per-point overlap weights in (0, 1] from source vs pseudo-target neighbourhood shapes."""

    def __init__(self, config: IFNetConfig):
        super().__init__()
        w, h = config.overlap_width, config.overlap_hidden

        def conv(c_in: int, c_out: int, kernel: tuple[int, int] = (1, 1)) -> list[nn.Module]:
            padding = (kernel[0] // 2, 0)
            return [nn.Conv2d(c_in, c_out, kernel, padding=padding), nn.BatchNorm2d(c_out), nn.LeakyReLU(0.2)]

        # v: EdgeConv along the k neighbours (3-wide kernels over the neighbour axis)
        self.edge_encoder = nn.Sequential(*conv(3, w, (3, 1)), *conv(w, 2 * w, (3, 1)))
        self.difference_mlp = nn.Sequential(*conv(2 * w, h), *conv(h, h))
        self.attention_mlp = nn.Sequential(*conv(2 * w, h), *conv(h, h))  # u
        self.head = nn.Sequential(  # f
            nn.Conv1d(h, h // 2, 1), nn.BatchNorm1d(h // 2), nn.LeakyReLU(0.2), nn.Conv1d(h // 2, 1, 1)
        )

    def encode(self, edges: Tensor) -> Tensor:
        return self.edge_encoder(edges.permute(0, 3, 2, 1))  # [B, N, k, 3] -> [B, 2w, k, N]

    def forward(self, source_edges: Tensor, pseudo_edges: Tensor) -> Tensor:
        # *_edges [B, N, k, 3] -> weights [B, N]
        difference = self.encode(source_edges) - self.encode(pseudo_edges)  # D_r, [B, 2w, k, N]
        values = self.difference_mlp(difference)  # [B, h, k, N]
        pooled = softmax_weighted_sum(self.attention_mlp(difference), values, dim=2)  # tau-weighted, [B, h, N]
        return 1.0 - torch.tanh(self.head(pooled).abs()).squeeze(1)


class CloudGraph(NamedTuple):
    """A cloud's kNN graphs; a rigid motion leaves them unchanged, so they are built once."""

    edgeconv: Tensor  # [B, N, k1], self first
    attention: Tensor  # [B, N, attention_k], self first
    attention_sq_distances: Tensor  # [B, N, attention_k] to those neighbours
    score: Tensor  # [B, N, k2 - 1], self excluded
    nearest_two: Tensor  # [B, N, 2], self excluded


class TargetContext(NamedTuple):
    """Everything about the target that is the same in every block (the target never moves)."""

    points: Tensor  # [B, M, 3]
    graph: CloudGraph
    descriptor: Tensor  # [B, M, 14]
    features: Tensor  # [B, M, C] low-level EdgeConv features


class BlockOutput(NamedTuple):
    rotation: Tensor  # [B, 3, 3] this block's increment
    translation: Tensor  # [B, 3]
    source: Tensor  # [B, N, 3] the block's input source
    pseudo_target: Tensor  # [B, N, 3] matching-matrix-weighted target points
    weights: Tensor  # [B, N] overlap weights
    matching: Tensor  # [B, N, M] final matching matrix
    target_features: Tensor  # [B, M, C] high-level target features (fed back)


class IFNetOutput(NamedTuple):
    rotation: Tensor  # [B, 3, 3] source -> target
    translation: Tensor  # [B, 3]
    blocks: list[BlockOutput]  # in execution order: time step major, iteration minor
    source_graph: CloudGraph


class FeedbackRegistrationBlock(nn.Module):
    """One FRB: features, feedback attention, matching, overlap weights, weighted Procrustes."""

    def __init__(self, config: IFNetConfig):
        super().__init__()
        self.config = config
        self.edgeconv = EdgeConv(config)
        self.feedback_transformer = FeedbackTransformer(config)
        self.matching_matrix = MatchingMatrix(config)
        self.overlap_predictor = OverlapPredictor(config)

    def build_graph(self, points: Tensor) -> CloudGraph:
        c = self.config
        sq_distances, idx = knn(points, points, c.graph_k)  # [B, N, graph_k] each, self first
        return CloudGraph(
            idx[..., : c.edgeconv_k],
            idx[..., : c.attention_k],
            sq_distances[..., : c.attention_k],
            idx[..., 1 : c.score_k],
            idx[..., 1:3],
        )

    def encode_target(self, target: Tensor) -> TargetContext:
        graph = self.build_graph(target)
        descriptor = geometry_descriptor(target, graph.nearest_two)
        return TargetContext(target, graph, descriptor, self.edgeconv(target, graph.edgeconv))

    def forward(
        self, source: Tensor, source_graph: CloudGraph, target: TargetContext, feedback: Tensor | None
    ) -> BlockOutput:
        # source [B, N, 3] in its current pose; feedback [B, M, C] or None at time step 0
        src_descriptor = geometry_descriptor(source, source_graph.nearest_two)
        src_low = self.edgeconv(source, source_graph.edgeconv)
        tgt_low = target.features if feedback is None else feedback
        attend = self.feedback_transformer
        src_high = attend(source, source_graph, src_descriptor, src_low, target.points, target.descriptor, tgt_low)
        tgt_high = attend(target.points, target.graph, target.descriptor, tgt_low, source, src_descriptor, src_high)

        matching = self.matching_matrix(src_high, tgt_high, source_graph.score, target.graph.score)
        pseudo_target = matching @ target.points  # [B, N, 3]
        # Edges as centre minus neighbour, the official code's sign for the overlap predictor.
        edges = source_graph.edgeconv
        weights = self.overlap_predictor(-neighbour_offsets(source, edges), -neighbour_offsets(pseudo_target, edges))
        rotation, translation = weighted_procrustes(source, pseudo_target, weights)
        return BlockOutput(rotation, translation, source, pseudo_target, weights, matching, tgt_high)


class IFNet(nn.Module):
    def __init__(self, config: IFNetConfig):
        super().__init__()
        self.config = config
        self.block = FeedbackRegistrationBlock(config)  # shared by all iterations and time steps

    def forward(self, source: Tensor, target: Tensor) -> IFNetOutput:
        # source [B, N, 3], target [B, M, 3]
        batch = source.shape[0]
        target_context = self.block.encode_target(target)
        source_graph = self.block.build_graph(source)
        feedback: list[Tensor | None] = [None] * self.config.n_iters
        blocks: list[BlockOutput] = []
        for _ in range(self.config.time_steps):
            rotation, translation = identity_transform(batch, source)
            moved = source
            for i in range(self.config.n_iters):
                out = self.block(moved, source_graph, target_context, feedback[i])
                feedback[i] = out.target_features
                rotation, translation = compose(rotation, translation, out.rotation, out.translation)
                moved = transform_points(moved, out.rotation, out.translation)
                blocks.append(out)
        return IFNetOutput(rotation, translation, blocks, source_graph)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
