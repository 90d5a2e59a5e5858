"""Export IFNet to a single static ONNX graph (time steps x iterations unrolled) and check it.

The exported interface is the project's public contract:
    inputs   source [batch, n_source, 3], target [batch, n_target, 3]   float32
    outputs  rotation [batch, 3, 3], translation [batch, 3]             float32
with target ~ source @ rotation^T + translation. Batch and both point counts are dynamic axes.
"""

import copy
import datetime as dt
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_linear_bn_eval

from model.geometry import rotation_angle_deg
from model.ifnet import ChannelBatchNorm, IFNet, PointMLP

OPSET = 17
MODEL_NAME = "ifnet"
DYNAMIC_AXES = {
    # The two clouds get separate symbolic point counts: one shared name fails when they differ.
    "source": {0: "batch", 1: "n_source"},
    "target": {0: "batch", 1: "n_target"},
    "rotation": {0: "batch"},
    "translation": {0: "batch"},
}


def fold_batch_norms(model: IFNet) -> IFNet:
    """An evaluation-mode copy of model with every BatchNorm after a linear layer folded into it.

    The same function with fewer operators: ONNX Runtime fuses a Conv's BatchNorm itself but not
    these (they sit behind reshapes). Fewer nodes mostly shorten the session's start-up.
    """
    folded = copy.deepcopy(model).eval()
    with torch.no_grad():
        for mlp in (m for m in folded.modules() if isinstance(m, PointMLP)):
            for i in range(len(mlp) - 1):
                if isinstance(mlp[i], nn.Linear) and isinstance(mlp[i + 1], ChannelBatchNorm):
                    mlp[i], mlp[i + 1] = fuse_linear_bn_eval(mlp[i], mlp[i + 1]), nn.Identity()
        # The attention MLP normalises a sum of attn_in outputs (query - key + attn_in(pos)), and
        # its bias enters that sum once, so the norm folds into attn_in itself.
        attention = folded.block.feedback_transformer
        attention.attn_in = fuse_linear_bn_eval(attention.attn_in, attention.attn_out[0])
        attention.attn_out[0] = nn.Identity()
    return folded


class RegistrationGraph(nn.Module):
    """IFNet reduced to the public contract: (source, target) -> (rotation, translation).

    BatchNorms are folded (`fold_batch_norms`), so the graph always computes the evaluation-mode
    model; the model passed in is left as it is.
    """

    def __init__(self, model: IFNet):
        super().__init__()
        self.model = fold_batch_norms(model)

    def forward(self, source: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
        out = self.model(source, target)
        return out.rotation, out.translation


def export_onnx(
    module: nn.Module,
    path: Path,
    example: tuple[Tensor, ...],
    input_names: list[str],
    output_names: list[str],
    dynamic_axes: dict,
    metadata: dict[str, str] | None = None,
) -> float:
    """Trace module to path (one file, no external data); returns the export time in seconds.

    The TorchScript-based exporter is used: far quicker than the dynamo exporter on the unrolled
    graph, and its graph runs faster in ONNX Runtime.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    # The exporter restores the wrapper's train/eval flag recursively after tracing: a wrapper
    # left in training mode would put the model's BatchNorms back into training mode.
    module.eval()
    started = time.perf_counter()
    # The TorchScript exporter is the deliberate choice (above): its deprecation notices say nothing new.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", "You are using the legacy TorchScript-based ONNX export", DeprecationWarning)
        warnings.filterwarnings("ignore", "The feature will be removed", DeprecationWarning)
        torch.onnx.export(
            module,
            example,
            str(path),
            input_names=input_names,
            output_names=output_names,
            dynamic_axes=dynamic_axes,
            opset_version=OPSET,
            dynamo=False,
        )
    seconds = time.perf_counter() - started
    if metadata:
        proto = onnx.load(str(path))
        onnx.helper.set_model_props(proto, metadata)
        onnx.save(proto, str(path))
    return seconds


@dataclass
class ParityReport:
    max_rotation_entry: float  # max |R_ort - R_torch| over entries
    max_translation_entry: float
    max_angle_difference_deg: float  # |error(ORT vs truth) - error(torch vs truth)|, when truth is known
    pairs: int

    def passes(self, rotation_tol: float, translation_tol: float, angle_tol_deg: float) -> bool:
        return (
            self.max_rotation_entry <= rotation_tol
            and self.max_translation_entry <= translation_tol
            and self.max_angle_difference_deg <= angle_tol_deg
        )


def compare_with_torch(session: ort.InferenceSession, model: IFNet, pairs: list[dict[str, np.ndarray]]) -> ParityReport:
    """Run both on the same pairs (one at a time) and report the largest differences."""
    model.eval()
    rot_diff = trans_diff = angle_diff = 0.0
    for pair in pairs:
        source, target = pair["source"][None], pair["target"][None]
        rot_ort, trans_ort = session.run(None, {"source": source, "target": target})
        with torch.no_grad():
            out = model(torch.from_numpy(source), torch.from_numpy(target))
        rot_torch, trans_torch = out.rotation.numpy(), out.translation.numpy()
        rot_diff = max(rot_diff, float(np.abs(rot_ort - rot_torch).max()))
        trans_diff = max(trans_diff, float(np.abs(trans_ort - trans_torch).max()))
        if "rotation" in pair:
            truth = pair["rotation"].astype(np.float64)
            err_ort = rotation_angle_deg(rot_ort[0].astype(np.float64), truth)
            err_torch = rotation_angle_deg(rot_torch[0].astype(np.float64), truth)
            angle_diff = max(angle_diff, float(abs(err_ort - err_torch)))
    return ParityReport(rot_diff, trans_diff, angle_diff, len(pairs))


def metadata_for(model: IFNet, preset_name: str, weights_sha256: str) -> dict[str, str]:
    """The metadata the service reads (`session.get_modelmeta().custom_metadata_map`)."""
    return {
        "model_name": MODEL_NAME,
        "preset": preset_name,
        "num_points": str(model.config.num_points),
        "min_points": str(model.config.graph_k),
        "weights_sha256": weights_sha256,
        "opset": str(OPSET),
        "export_date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "config": json.dumps(model.config.to_dict()),
        "interface": "target ~ source @ rotation^T + translation",
    }
