"""Reading IFNet weights: shipped weights files and training checkpoints, with their checksum and preset."""

import json
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

from model.artifacts import file_sha256
from model.cli import UserError, load_torch_file
from model.ifnet import IFNet, IFNetConfig


def read_weights(path: Path, what: str) -> dict:
    """The state of shipped weights or a training checkpoint (model state and config at least), or a
    UserError naming `what` (the option or role of the file) and the path."""
    state = load_torch_file(path, what)
    if "model" not in state or "config" not in state:
        raise UserError(f"{what} {path}: not IFNet weights or a training checkpoint (no model state and config)")
    return state


def shipped_record(weights: str | Path | None) -> dict | None:
    """The training record shipped beside `weights` (its .json), as a later leg keeps it: file, sha256,
    training and date; None where there is none."""
    record = Path(weights).with_suffix(".json") if weights else None
    if record is None or not record.is_file():
        return None
    shipped = json.loads(record.read_text())
    return {name: shipped[name] for name in ("file", "sha256", "training", "date") if name in shipped}


def weights_preset(state: dict) -> str:
    """The preset a weights file or checkpoint was trained as (checkpoints before the top-level
    entry kept it only among their arguments); "custom" where neither says."""
    return state.get("preset") or state.get("args", {}).get("preset") or "custom"


class LoadedWeights(NamedTuple):
    model: IFNet  # in eval mode
    sha256: str  # of the file
    preset: str


def load_checkpoint(
    path: Path, iterations: int | None = None, time_steps: int | None = None, num_points: int | None = None
) -> LoadedWeights:
    """The model in eval mode from a training checkpoint or shipped weights, the file's sha256 and
    its preset.

    `iterations` and `time_steps` override the unroll the weights were trained with (`n_iters`
    blocks per time step, `time_steps` passes with the target features fed back): every block
    runs the same shared weights, so the weights run at any counts, and the cost grows with
    their product. `num_points` overrides the native point count (the count the service
    resamples each cloud to); the graph runs at any count from the config's `graph_k`.
    """
    state = read_weights(path, "weights file")
    config = IFNetConfig.from_dict(state["config"])
    overrides = {"n_iters": iterations, "time_steps": time_steps, "num_points": num_points}
    config = replace(config, **{k: v for k, v in overrides.items() if v is not None})  # rejects counts below 1
    model = IFNet(config)
    model.load_state_dict(state["model"])
    return LoadedWeights(model.eval(), file_sha256(path), weights_preset(state))
