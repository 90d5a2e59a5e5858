"""Does an indoor network fit the scenes it was trained on better than the held-out ones? Rotation
error alone of ONNX files on one pair per scan of each part (the paper's indoor protocol, two
captures, bench.harness.scene_pairs), by
scene, and on the same pairs with their motion removed (the source laid on the target): what the
network answers where the right answer is no motion at all.

    PYTHONPATH=. python docs/training/experiments/indoor_fit.py service/models/indoor.onnx <other exports>
"""

import argparse
import collections
from pathlib import Path

import numpy as np

from bench import harness
from model.geometry import apply_transform
from model.training.scenes import scene_of


def error_alone(network: harness.Network, pair: harness.Pair) -> float:
    return harness.errors(pair, *network.answer(pair)[:2])["rotation_deg"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", type=Path, nargs="+")
    args = parser.parse_args()
    networks = [harness.Network(path, 2) for path in args.models]
    print("rotation error alone, deg, per file: mean / median as built, then mean / median with no motion")
    for part in ("train", "test"):
        moved, still = [], []
        by_scene = collections.defaultdict(list)
        for pair in harness.scene_pairs("indoor", part=part):
            laid = apply_transform(pair.source, pair.rotation, pair.translation)
            aligned = harness.Pair(pair.name, laid, pair.target, np.eye(3), np.zeros(3), pair.voxel)
            moved.append([error_alone(network, pair) for network in networks])
            still.append([error_alone(network, aligned) for network in networks])
            by_scene[scene_of(pair.name.split("/")[1])].append(moved[-1])
        print(f"{part}: {len(moved)} pairs")
        for i, path in enumerate(args.models):
            errors, resting = np.array(moved)[:, i], np.array(still)[:, i]
            print(
                f"  {str(path):40s} {errors.mean():6.2f} / {np.median(errors):5.2f}"
                f"   no motion {resting.mean():5.2f} / {np.median(resting):5.2f}"
            )
        for scene, rows in sorted(by_scene.items(), key=lambda item: -len(item[1])):
            means = " ".join(f"{mean:6.2f}" for mean in np.array(rows).mean(axis=0))
            print(f"    {scene:40s} {len(rows):3d} pairs  {means}")


if __name__ == "__main__":
    main()
