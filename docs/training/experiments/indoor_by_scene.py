"""Rotation error alone of ONNX files on the held-out indoor pairs (two captures), by scene: where
the mean comes from.

    PYTHONPATH=. python docs/training/experiments/indoor_by_scene.py service/models/indoor.onnx <other exports>
"""

import argparse
import collections
from pathlib import Path

import numpy as np

from bench import harness
from model.training.scenes import scene_of

FAR_DEG = 10.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", type=Path, nargs="+")
    args = parser.parse_args()
    networks = [harness.Network(path, 2) for path in args.models]
    by_scene = collections.defaultdict(list)
    for pair in harness.scene_pairs("indoor"):
        errors = []
        for network in networks:
            errors.append(harness.errors(pair, *network.answer(pair)[:2])["rotation_deg"])
        by_scene[scene_of(pair.name.split("/")[1])].append(errors)
    print(f"rotation error alone, deg: mean per file, then pairs over {FAR_DEG:g} deg per file")
    for scene, rows in sorted(by_scene.items(), key=lambda item: -np.mean([row[0] for row in item[1]])):
        errors = np.array(rows)
        means = " ".join(f"{mean:6.2f}" for mean in errors.mean(axis=0))
        far = " ".join(str(count) for count in (errors > FAR_DEG).sum(axis=0))
        print(f"  {scene:28s} {len(errors):3d} pairs  {means}   {far}")
    errors = np.array([row for rows in by_scene.values() for row in rows])
    for i, path in enumerate(args.models):
        far = errors[:, i] > FAR_DEG
        share = errors[far, i].sum() / errors[:, i].sum()
        print(f"{path}: mean {errors[:, i].mean():.2f}, {far.sum()} pairs over {FAR_DEG:g} deg carry {share:.0%} of it")


if __name__ == "__main__":
    main()
