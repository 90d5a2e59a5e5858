"""Does averaging each point with its neighbours give jittered pairs back their shared points?

Each cloud's points are replaced by the mean of their k nearest neighbours (itself included)
before the network sees them. The mean is rigid-equivariant, so the pose between the smoothed
clouds is the true one, and the independent jitter of the two clouds shrinks by sqrt(k).
Prints MAE(R) of the network alone on the first --pairs evaluation pairs of each variant:

    python -m export --weights model/weights/ifnet-fast-clean.pt --output /tmp/ifnet-clean.onnx
    python docs/training/experiments/input_smoothing.py --model /tmp/ifnet-clean.onnx --k 1 4 8 16 32

(The table in README.md is of the clean-trained network, as above; the default --model is the
shipped one.)
"""

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from model.geometry import registration_errors
from model.training.data import evaluation_pairs
from model.training.evaluate import network_runner


def neighbourhood_mean(points: np.ndarray, k: int) -> np.ndarray:
    if k == 1:
        return points
    _, idx = cKDTree(points).query(points, k)
    return points[idx].mean(axis=1).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=Path("service/models/object.onnx"))
    parser.add_argument("--k", type=int, nargs="+", default=[1, 4, 8, 16, 32])
    parser.add_argument("--pairs", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1234, help="the evaluation's pair seed")
    args = parser.parse_args()

    network = network_runner(args.model, threads=2)
    for noise in ("clean", "jitter", "outliers"):
        pairs = evaluation_pairs(args.pairs, noise, args.seed)
        true_rotations = np.array([pair["rotation"] for pair in pairs], np.float64)
        true_translations = np.array([pair["translation"] for pair in pairs], np.float64)
        for k in args.k:
            rotations, translations = [], []
            for pair in pairs:
                rotation, translation = network(
                    neighbourhood_mean(pair["source"], k), neighbourhood_mean(pair["target"], k)
                )
                rotations.append(rotation)
                translations.append(translation)
            errors = registration_errors(np.array(rotations), np.array(translations), true_rotations, true_translations)
            print(
                f"{noise:8s} k={k:2d}: MAE(R) {errors['euler_abs'].mean():.3f} deg, "
                f"median rotation error {np.median(errors['rotation_deg']):.3f} deg, "
                f"{(errors['rotation_deg'] > 5).sum()} of {len(pairs)} pairs off by more than 5 deg"
            )


if __name__ == "__main__":
    main()
