"""How close can a refined answer get on the held-out scene pairs? GICP started from the true pose.

Refinement moves even the true pose to the nearest optimum of its own fit; where the two clouds are
separate samples of a scan, that optimum lies off the truth, and no network answer refined by it
does better on average. Per domain and kind of pair (two disjoint samples, the project's protocol;
or one sample moved, as the paper builds its pairs, which share every point of their overlap),
the paper's MAE(R) (mean absolute Euler-angle error, degrees) and the median rotation error after
`model.geometry.refine` (the service's GICP), per scene and overall:

    PYTHONPATH=. python docs/training/experiments/refinement_floor.py --scene-pairs 1
"""

import argparse
from collections import defaultdict

import numpy as np

from bench import harness
from model.geometry import refine
from model.training.scenes import scene_of


def summary(rows) -> str:
    rows = np.asarray(rows)
    return f"{len(rows):3d} pairs, MAE(R) {rows[:, 0].mean():.4f}, median {np.median(rows[:, 1]):.4f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene-pairs", type=int, default=1, help="pairs per held-out scan")
    args = parser.parse_args()
    for domain in ("indoor", "outdoor"):
        for shared in (False, True):
            by_scene = defaultdict(list)
            for pair in harness.scene_pairs(domain, args.scene_pairs, shared=shared):
                rotation, translation, _ = refine(pair.source, pair.target, pair.rotation, pair.translation)
                errors = harness.errors(pair, rotation, translation)
                by_scene[scene_of(pair.name.split("/")[1])].append(
                    (np.mean(errors["euler_abs_deg"]), errors["rotation_deg"])
                )
            kind = "one sample moved (paper)" if shared else "disjoint samples"
            print(f"{domain}, {kind}: {summary([row for rows in by_scene.values() for row in rows])}")
            for scene, rows in sorted(by_scene.items()):
                print(f"    {scene:32s} {summary(rows)}")


if __name__ == "__main__":
    main()
