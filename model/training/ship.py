"""Turn a training checkpoint into the shipped weights and their metadata record.

    python -m model.training.ship --checkpoint runs/fast/checkpoint.pt
    python -m model.training.ship --evaluation docs/evaluation/evaluation.json   # add the eval summary

Writes model/weights/ifnet-<preset>.pt (or the --weights path: model state and config only, no
optimiser) and the record beside it, ifnet-<preset>.json (preset, training data and noise, steps and
epochs, date, checksum, evaluation). With --evaluation alone it updates the record of --weights
(default: the shipped model/weights/ifnet-fast.pt).
"""

import argparse
import csv
import datetime as dt
import json
from pathlib import Path

import torch

from model.artifacts import DEFAULT_WEIGHTS, file_sha256
from model.checkpoint import shipped_record, weights_preset
from model.cli import UserError, load_torch_file, reports_user_errors
from model.training.scenes import HELD_OUT_SCENES, SCAN_FILES

PROG = "python -m model.training.ship"

TRAINING_DATA = "ModelNet10 train split (../shared/data/modelnet10_train.npz), last 64 shapes held out for validation"


def training_data(args: dict) -> str:
    """What a checkpoint was trained on, from its recorded command-line arguments."""
    domain = args.get("domain", "object")
    if domain == "object":
        data = TRAINING_DATA
    else:
        data = (
            f"real {domain} scans (../shared/data/{SCAN_FILES[domain]}) of every scene but the held-out "
            f"{', '.join(HELD_OUT_SCENES[domain])}; the paper's {domain} protocol (model/training/scenes.py)"
        )
    if args.get("init_weights"):
        data += f"; fine-tuned from {args['init_weights']}"
    return data


def training_objective(args: dict) -> str:
    """The losses a checkpoint was trained with, from its recorded command-line arguments."""
    objective = "the paper's three unsupervised losses"
    if args.get("global_loss", "squared") != "squared":
        objective += f", global loss on {args['global_loss']}s"
    if args.get("global_weight", 1.0) != 1.0:
        objective += f", global loss weighted {args['global_weight']:g}"
    if args.get("teacher"):
        objective += f", plus teacher consistency with {args['teacher']} (weight {args['teacher_weight']:g})"
        if args.get("domain", "object") != "object":
            objective += ", its estimate on the shared-point pair polished by GICP, kept where shared points coincide"
    return objective


def pair_noise(args: dict) -> str:
    """The noise of the pairs a checkpoint was trained on (runs before `--noise` existed: clean)."""
    if args.get("domain", "object") != "object":
        return "two captures: each cloud drawn from its own half of the scan, no shared point"
    noise = args.get("noise", ["clean"])
    if "jitter" in noise:
        return ", ".join(noise) + f" mixed pair by pair, jitter sigma {args['jitter_sigma']:g}"
    return ", ".join(noise)


def earlier_training(state: dict) -> dict | None:
    """The record of the shipped weights a run was fine-tuned from: a later leg of training keeps the
    history of the legs before it (its weights may replace the earlier ones). train keeps it in the
    checkpoint from the run's start; for older checkpoints it is read from beside the weights."""
    if "fine_tuned_from" in state:
        return state["fine_tuned_from"]
    return shipped_record(state["args"].get("init_weights"))


def read_checkpoint(checkpoint: Path) -> dict:
    state = load_torch_file(checkpoint, "--checkpoint")
    if not {"model", "config", "args", "step"} <= set(state):
        raise UserError(
            f"--checkpoint {checkpoint}: not a training checkpoint (shipped weights carry no training record); "
            "pass the checkpoint.pt of a training run"
        )
    return state


def ship(state: dict, checkpoint: Path, weights: Path) -> dict:
    preset_name = weights_preset(state)
    earlier = earlier_training(state)  # read before the weights (perhaps the same file) are replaced
    weights.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": state["model"], "config": state["config"], "preset": preset_name}, weights)
    log_path = checkpoint.parent / "log.csv"
    rows = list(csv.DictReader(log_path.open())) if log_path.exists() else []
    validations = [r for r in rows if r["val_rotation_deg"]]
    return {
        "file": weights.name,
        "sha256": file_sha256(weights),
        "preset": preset_name,
        "config": state["config"],
        "parameters": sum(
            v.numel()
            for k, v in state["model"].items()
            if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))
        ),
        "training": {
            "data": training_data(state["args"]),
            "objective": training_objective(state["args"]),
            "pair_noise": pair_noise(state["args"]),
            "steps": state["step"],
            "epochs": float(rows[-1]["epoch"]) if rows else None,
            "batch_size": state["args"]["batch_size"],
            "optimiser": f"Adam, lr {state['args']['lr']}, {state['args']['schedule']} schedule",
            "seed": state["args"]["seed"],
            "hours_on_2_cpu_cores": round(float(rows[-1]["seconds"]) / 3600, 2) if rows else None,
            "final_validation_rotation_deg": float(validations[-1]["val_rotation_deg"]) if validations else None,
        }
        | ({"fine_tuned_from": earlier} if earlier else {}),
        "date": dt.date.today().isoformat(),
    }


def evaluation_results(path: Path) -> dict:
    try:
        return json.loads(path.read_text())["results"]
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        raise UserError(f"--evaluation {path}: not an evaluation.json of python -m model.training.evaluate") from None


@reports_user_errors(PROG)
def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, help="training checkpoint to ship")
    parser.add_argument(
        "--weights",
        type=Path,
        help="where the weights go (default: model/weights/ifnet-<the checkpoint's preset>.pt; with only "
        "--evaluation, the shipped model/weights/ifnet-fast.pt)",
    )
    parser.add_argument("--evaluation", type=Path, help="evaluation.json whose summary goes into the record")
    args = parser.parse_args(argv)
    if not (args.checkpoint or args.evaluation):
        parser.error("give --checkpoint (ship a training run) and/or --evaluation (add its summary to the record)")
    state = read_checkpoint(args.checkpoint) if args.checkpoint else None
    if args.weights is None:
        args.weights = DEFAULT_WEIGHTS.with_name(f"ifnet-{weights_preset(state)}.pt") if state else DEFAULT_WEIGHTS
    record_path = args.weights.with_suffix(".json")
    if state is None and not record_path.is_file():
        raise UserError(f"{record_path} not found: ship a checkpoint first (--checkpoint)")
    record = ship(state, args.checkpoint, args.weights) if state else json.loads(record_path.read_text())
    if record["sha256"] != file_sha256(args.weights):
        raise UserError(f"{record_path} does not describe {args.weights} (checksum differs); ship again")
    if args.evaluation:
        results = evaluation_results(args.evaluation)
        record["evaluation"] = {
            set_name: {
                method: {
                    k: round(v, 6)
                    for k, v in s.items()
                    if k in ("mae_r", "mae_t", "iso_r_mean", "recall_1deg_001", "ms_per_pair")
                }
                for method, s in rows.items()
            }
            for set_name, rows in results.items()
        }
    record_path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {args.weights} and {record_path}" if args.checkpoint else f"wrote {record_path}")


if __name__ == "__main__":
    main()
