"""Which network registers real scans taken twice? Pairs whose clouds share no exact points.

A second capture of a scene samples the same surfaces at other points. Each real scan's
distinct points are split at random into two disjoint halves; the target is the second half
moved by the training protocol's motion (Euler angles in [0, 45] degrees, translation up to
half the scan's radius per axis), and each half is cropped to the fraction `--overlap` (0.75)
of its points nearest one shared far point (a partial view, as in training). The control
("shared") moves the whole scan onto itself, so both clouds hold the same points. Every pair
goes through the service's own path (`register_clouds`: sampling, normalisation, the ONNX
model, ICP with `refine`), once per model:

    python -m export --weights model/weights/ifnet-fast-clean.pt --output /tmp/ifnet-clean.onnx
    python docs/training/experiments/real_scan_pairs.py \
        --models service/models/object.onnx /tmp/ifnet-clean.onnx --motions 5

Prints, per model, scan and kind of pair, the median and worst rotation error (degrees) of the
network alone and after refinement, and how many pairs are more than 5 degrees off; writes every
pair's errors to `--out` (default: real_scan_pairs.json beside this script).
"""

import argparse
import asyncio
import json
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from model.geometry import (
    apply_transform,
    crop_nearest,
    disjoint_halves,
    from_matrix,
    random_rotation,
    remove_duplicates,
    rotation_angle_deg,
)
from service.batcher import Prediction
from service.engine import OnnxEngine
from service.registration import Network, register_clouds
from service.schemas import RefineOptions, RegistrationOptions
from service.settings import Settings

REAL_SCANS = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "real_scans.npz"


def rescan_pair(scan: np.ndarray, rng: np.random.Generator, overlap: float) -> tuple[np.ndarray, np.ndarray]:
    """Two disjoint random halves of the scan, each cropped to `overlap` of its points near one far point."""
    first, second = disjoint_halves(scan, rng)
    if overlap < 1.0:
        centre = scan.mean(axis=0)
        direction = rng.normal(size=3)
        anchor = centre + direction / np.linalg.norm(direction) * 10.0 * np.abs(scan - centre).max()
        first = crop_nearest(first, anchor, int(overlap * len(first)))
        second = crop_nearest(second, anchor, int(overlap * len(second)))
    return first, second


def rotation_errors(engine: OnnxEngine, pairs) -> tuple[np.ndarray, np.ndarray]:
    """Rotation errors (deg) of the network alone and after refinement, from one refined call per
    pair: the refinement report keeps the network's transform."""

    async def predict(source: np.ndarray, target: np.ndarray) -> Prediction:
        rotation, translation = engine.run(source[None], target[None])
        return Prediction(rotation[0], translation[0])

    options = RegistrationOptions(refine=RefineOptions())
    networks = [Network(engine.info.name, engine.info.network_points, predict)]
    alone, refined = [], []
    for source, target, true_rotation in pairs:
        result = asyncio.run(register_clouds(source, target, options, Settings(), networks, run_blocking=_inline))
        alone.append(float(rotation_angle_deg(from_matrix(result.refinement.network_transform)[0], true_rotation)))
        refined.append(float(rotation_angle_deg(result.rotation, true_rotation)))
    return np.array(alone), np.array(refined)


async def _inline(function, *args):
    return function(*args)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", type=Path, nargs="+", default=[Path("service/models/object.onnx")])
    parser.add_argument("--motions", type=int, default=5, help="random motions per scan and kind of pair")
    parser.add_argument("--overlap", type=float, default=0.75)
    parser.add_argument("--max-points", type=int, default=40_000, help="larger scans are subsampled first")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).with_suffix(".json"))
    args = parser.parse_args()
    record: dict = {
        "command": " ".join(["python docs/training/experiments/real_scan_pairs.py", *sys.argv[1:]]),
        "when": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "models": {},
    }

    with np.load(REAL_SCANS, allow_pickle=False) as archive:
        scans = {name: remove_duplicates(archive[name].astype(np.float64)) for name in archive.files}
    rng = np.random.default_rng(args.seed)
    pairs: dict[tuple[str, str], list] = {}
    for name, scan in scans.items():
        if len(scan) > args.max_points:
            scan = scan[rng.choice(len(scan), args.max_points, replace=False)]
        radius = np.linalg.norm(scan - scan.mean(axis=0), axis=1).max()
        for kind in ("shared", "rescan"):
            pairs[name, kind] = []
            for _ in range(args.motions):
                rotation, _ = random_rotation(rng)
                translation = rng.uniform(-0.5, 0.5, 3) * radius
                source, target = (scan, scan) if kind == "shared" else rescan_pair(scan, rng, args.overlap)
                pairs[name, kind].append((source, apply_transform(target, rotation, translation), rotation))

    for model in args.models:
        engine = OnnxEngine(model, threads=2)
        print(f"\n{model}: rotation error, median / worst of {args.motions} motions (deg), (pairs above 5 deg)")
        print(f"{'scan':24s} {'pair':7s} {'points':>7s} {'network':>19s} {'refined':>19s}")
        summary: dict[str, list[np.ndarray]] = {"shared": [], "rescan": []}
        rows = record["models"][str(model)] = []
        for (name, kind), scan_pairs in pairs.items():
            alone, refined = rotation_errors(engine, scan_pairs)
            summary[kind].append(np.stack([alone, refined]))
            rows.append(
                {
                    "scan": name,
                    "pair": kind,
                    "source_points": len(scan_pairs[0][0]),
                    "network_deg": alone.tolist(),
                    "refined_deg": refined.tolist(),
                }
            )
            cells = [f"{np.median(e):7.3f} / {e.max():6.2f} ({(e > 5).sum()})" for e in (alone, refined)]
            print(f"{name:24s} {kind:7s} {len(scan_pairs[0][0]):7d} {cells[0]:>19s} {cells[1]:>19s}")
        for kind, stacks in summary.items():
            alone, refined = np.concatenate(stacks, axis=1)
            print(
                f"all scans, {kind}: median {np.median(alone):.3f} / {np.median(refined):.3f} deg, "
                f"{(alone > 5).sum()} / {(refined > 5).sum()} of {len(alone)} pairs above 5 deg "
                "(network / refined)"
            )
    args.out.write_text(json.dumps(record, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
