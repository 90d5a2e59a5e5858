"""Does averaging each point with its neighbours give jittered pairs back their shared points?

Each cloud's points are replaced by the mean of their k nearest neighbours (itself included)
before the network sees them. The mean is rigid-equivariant, so the pose between the smoothed
clouds is the true one, and the independent jitter of the two clouds shrinks by sqrt(k).
Prints MAE(R) of the network alone on the first --pairs evaluation pairs of each variant:

    python docs/training/experiments/input_smoothing.py --model service/models/ifnet.onnx --k 1 4 8 16 32
"""

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from export.onnx_export import ort_session
from model.geometry import registration_errors
from model.training.data import Protocol, load_split, make_pair


def neighbourhood_mean(points: np.ndarray, k: int) -> np.ndarray:
    if k == 1:
        return points
    _, idx = cKDTree(points).query(points, k)
    return points[idx].mean(axis=1).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=Path("service/models/ifnet.onnx"))
    parser.add_argument("--k", type=int, nargs="+", default=[1, 4, 8, 16, 32])
    parser.add_argument("--pairs", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1234, help="the evaluation's pair seed")
    args = parser.parse_args()

    session = ort_session(args.model, 2)
    shapes = load_split("same")[: args.pairs]
    for noise in ("clean", "jitter", "outliers"):
        protocol = Protocol(noise=noise)
        pairs = [make_pair(shape, protocol, np.random.default_rng((args.seed, i))) for i, shape in enumerate(shapes)]
        true_rotations = np.array([pair["rotation"] for pair in pairs], np.float64)
        true_translations = np.array([pair["translation"] for pair in pairs], np.float64)
        for k in args.k:
            rotations, translations = [], []
            for pair in pairs:
                feeds = {name: neighbourhood_mean(pair[name], k)[None] for name in ("source", "target")}
                rotation, translation = session.run(None, feeds)
                rotations.append(rotation[0])
                translations.append(translation[0])
            errors = registration_errors(
                np.array(rotations, np.float64), np.array(translations, np.float64), true_rotations, true_translations
            )
            print(
                f"{noise:8s} k={k:2d}: MAE(R) {errors['euler_abs'].mean():.3f} deg, "
                f"median rotation error {np.median(errors['rotation_deg']):.3f} deg, "
                f"{(errors['rotation_deg'] > 5).sum()} of {len(pairs)} pairs off by more than 5 deg"
            )


if __name__ == "__main__":
    main()
