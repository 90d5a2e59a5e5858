"""How well a coarse answer must match after refinement's coarse pass to come out of the fine pass
right and verified (or right and unpinned): the evidence behind
service.registration.FINE_PASS_MIN_FITNESS.

    python -m bench.fine_pass --set scans:12000 --seed 0 --every 2 [--as network]

For each view of the set (bench.harness.pair_set; every `--every`-th) large enough that the coarse
pass runs on a subset of the check's clouds: the truth turned by each of `--degrees` about a random
axis through the source's centre and shifted by up to 5 % of the extent, `--turns` times, refined
and checked as a rotated start's answer is (service.registration._checked, the fine pass never
skipped), or with `--as network` as a network's (its lower fitness bar). Printed per turn angle: how
many answers ended right and verified, and the lowest share of the source those matched after the
coarse pass, within LOOSE_SPACINGS and within INLIER_SPACINGS point spacings; the same for those
ended right and unpinned (failing only on the constraint). Right: rotation error <= 2 degrees and
translation error <= 2 % of the extent.
"""

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench import harness
from model.geometry import INLIER_SPACINGS, MIN_FITNESS, extent
from service import registration
from service.registration import LOOSE_SPACINGS, MIN_STARTS_FITNESS, REFINE_MAX_SECONDS
from service.schemas import RefineOptions, RegistrationOptions
from service.settings import Settings


def trials(
    pair: harness.Pair, degrees: list[float], turns: int, rng: np.random.Generator, min_fitness: float
) -> list[dict]:
    settings, options = Settings(), RegistrationOptions(method="auto", refine=RefineOptions())
    prepared = registration._prepare(pair.source, pair.target, 384, options, settings, settings.threads)
    if prepared.coarse is prepared.check:
        return []
    coarse_distance = registration.refine_distances(prepared.check.spacing, prepared.normalisation.scale)[0]
    refine = RefineOptions()  # as a start's answer is refined
    centre, size = pair.source.mean(axis=0), extent(pair.target)
    rows = []
    for angle in degrees:
        for _ in range(turns):
            axis = rng.normal(size=3)
            turn = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).as_matrix()
            shift = rng.normal(size=3)
            shift *= rng.uniform(0.0, 0.05) * size / np.linalg.norm(shift)
            rotation = turn @ pair.rotation
            translation = pair.rotation @ centre + pair.translation - rotation @ centre + shift
            coarse = prepared.coarse.refine(
                rotation,
                translation,
                coarse_distance,
                max_iterations=refine.max_iterations,
                max_seconds=REFINE_MAX_SECONDS,
            )[:2]
            candidate = registration._checked(prepared, rotation, translation, refine, min_fitness)
            verdict = harness.errors(pair, candidate.rotation, candidate.translation)
            rows.append(
                {
                    "pair": pair.name,
                    "degrees": angle,
                    "loose": prepared.check.fitness(prepared.scored, *coarse, LOOSE_SPACINGS),
                    "tight": prepared.check.fitness(prepared.scored, *coarse, INLIER_SPACINGS),
                    "right": verdict["right"],
                    "verified": candidate.verification.verified,
                    "unpinned": candidate.verification.unpinned,
                    "fitness": candidate.verification.score.fitness,
                }
            )
    return rows


def lowest(rows: list[dict]) -> str:
    if not rows:
        return "-"
    return f"{min(row['loose'] for row in rows):.3f} loose, {min(row['tight'] for row in rows):.3f} tight"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--set", default="scans:12000", help="a set of views of real scans (bench.harness.pair_set)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--every", type=int, default=1, help="every n-th view of the set")
    p.add_argument("--degrees", type=float, nargs="+", default=[3.0, 6.0, 10.0, 15.0, 25.0, 40.0])
    p.add_argument("--turns", type=int, default=2, help="turns per angle and view")
    p.add_argument("--as", dest="kind", choices=["start", "network"], default="start", help="checked as whose answer")
    p.add_argument("--out", type=Path, help="write every trial here as JSON")
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    for pair in harness.pair_set(args.set, seed=args.seed)[:: args.every]:
        rows += trials(pair, args.degrees, args.turns, rng, MIN_STARTS_FITNESS if args.kind == "start" else MIN_FITNESS)
    print(f"{len(rows)} trials on thinned views, checked as a {args.kind}'s answer")
    for outcome in ("verified", "unpinned"):
        good = [row for row in rows if row["right"] and row[outcome]]
        print(f"right and {outcome}: {len(good)}")
        for angle in args.degrees:
            ended = [row for row in good if row["degrees"] == angle]
            print(f"  {angle:5.1f} deg: {len(ended):4d}, lowest fit after coarse {lowest(ended)}")
        print(f"  all: lowest fit after coarse {lowest(good)}")
    if args.out:
        harness.write_record(args.out, harness.run_header() | {"trials": rows})


if __name__ == "__main__":
    main()
