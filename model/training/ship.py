"""Turn a training checkpoint into the shipped weights and their metadata record.

    python -m model.training.ship --checkpoint runs/fast/checkpoint.pt
    python -m model.training.ship --evaluation docs/evaluation/evaluation.json   # add the eval summary

Writes model/weights/ifnet-<preset>.pt (or the --weights path: model state and config only, no
optimiser) and the record beside it, ifnet-<preset>.json (preset, training data and noise, steps and
epochs, date, checksum, evaluation).
"""

import argparse
import csv
import datetime as dt
import json
from pathlib import Path

import torch

from export.onnx_export import DEFAULT_WEIGHTS
from service.engine import file_sha256

TRAINING_DATA = "ModelNet10 train split (../shared/data/modelnet10_train.npz), last 64 shapes held out for validation"


def training_objective(args: dict) -> str:
    """The losses a checkpoint was trained with, from its recorded command-line arguments."""
    objective = "the paper's three unsupervised losses"
    if args.get("global_loss", "squared") != "squared":
        objective += f", global loss on {args['global_loss']}s"
    if args.get("global_weight", 1.0) != 1.0:
        objective += f", global loss weighted {args['global_weight']:g}"
    if args.get("teacher"):
        objective += f", plus teacher consistency with {args['teacher']} (weight {args['teacher_weight']:g})"
    return objective


def pair_noise(args: dict) -> str:
    """The noise of the pairs a checkpoint was trained on (runs before `--noise` existed: clean)."""
    noise = args.get("noise", ["clean"])
    if "jitter" in noise:
        return ", ".join(noise) + f" mixed pair by pair, jitter sigma {args['jitter_sigma']:g}"
    return ", ".join(noise)


def ship(checkpoint: Path, weights: Path) -> dict:
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    preset_name = state.get("preset") or state["args"]["preset"]
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
            "data": TRAINING_DATA,
            "objective": training_objective(state["args"]),
            "pair_noise": pair_noise(state["args"]),
            "steps": state["step"],
            "epochs": float(rows[-1]["epoch"]) if rows else None,
            "batch_size": state["args"]["batch_size"],
            "optimiser": f"Adam, lr {state['args']['lr']}, {state['args']['schedule']} schedule",
            "seed": state["args"]["seed"],
            "hours_on_2_cpu_cores": round(float(rows[-1]["seconds"]) / 3600, 2) if rows else None,
            "final_validation_rotation_deg": float(validations[-1]["val_rotation_deg"]) if validations else None,
        },
        "date": dt.date.today().isoformat(),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, help="training checkpoint to ship")
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--evaluation", type=Path, help="evaluation.json whose summary goes into the record")
    args = parser.parse_args(argv)
    record_path = args.weights.with_suffix(".json")
    record = ship(args.checkpoint, args.weights) if args.checkpoint else json.loads(record_path.read_text())
    if record["sha256"] != file_sha256(args.weights):
        raise SystemExit(f"{record_path} does not describe {args.weights} (checksum differs); ship again")
    if args.evaluation:
        results = json.loads(args.evaluation.read_text())["results"]
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
