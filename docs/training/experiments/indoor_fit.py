"""Does an indoor network fit the scenes it was trained on better than the held-out ones? Rotation
error alone of ONNX files on one pair per scan of each part (the paper's indoor protocol, two
captures, pair i seeded by (0, i, 0) as bench.harness.scene_pairs seeds the held-out pairs), by
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
from model.training.scenes import PROTOCOLS, load_scans, make_scan_pair, scene_of


def error_alone(network: harness.Network, pair: harness.Pair) -> float:
    feeds, normalisation = network.prepare(pair.source, pair.target)
    return harness.errors(pair, *network.to_user_units(normalisation, *network.call(feeds)))["rotation_deg"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", type=Path, nargs="+")
    args = parser.parse_args()
    networks = [harness.Network(path, 2) for path in args.models]
    print("rotation error alone, deg, per file: mean / median as built, then mean / median with no motion")
    for part in ("train", "test"):
        moved, still = [], []
        by_scene = collections.defaultdict(list)
        for i, (name, scan) in enumerate(load_scans("indoor", part, harness.DATA).items()):
            built = make_scan_pair(scan, PROTOCOLS["indoor"], np.random.default_rng((0, i, 0)))
            rotation, translation = built["rotation"], built["translation"]
            pair = harness.Pair(
                name, built["source"], built["target"], rotation, translation, harness.VOXEL_OBJECTS_INDOOR
            )
            laid = apply_transform(pair.source, rotation, translation)
            aligned = harness.Pair(name, laid, pair.target, np.eye(3), np.zeros(3), pair.voxel)
            moved.append([error_alone(network, pair) for network in networks])
            still.append([error_alone(network, aligned) for network in networks])
            by_scene[scene_of(name)].append(moved[-1])
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
