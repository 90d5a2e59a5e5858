"""Mean held-out rotation error (deg) of weights on the validation pairs a scene training run logs,
so that weights from different runs are compared on the same pairs (a run's pairs follow its seed).

    PYTHONPATH=. python docs/training/experiments/scene_validation.py model/weights/ifnet-indoor.pt --seed 3408
"""

import argparse
from pathlib import Path

import torch

from model.checkpoint import load_checkpoint
from model.training.train import parse_args, scene_pairs, validate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("weights", type=Path, help="shipped weights or a training checkpoint")
    parser.add_argument("--domain", default="indoor", choices=["indoor", "outdoor"])
    parser.add_argument("--seed", type=int, default=3407, help="the training run's --seed")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_checkpoint(args.weights).model
    run = parse_args(["--domain", args.domain, "--seed", str(args.seed)])  # the run's defaults, as it built them
    _, validation = scene_pairs(run, model.config)
    print(f"{args.weights}: {validate(model, validation['val_rotation_deg'], 'cpu', 4):.2f} deg")


if __name__ == "__main__":
    main()
