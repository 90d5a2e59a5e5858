"""Which scene training pairs a polished teacher teaches, and how far off its pose is.

For each pair: the teacher's estimate on the pair's shared-point version, polished by GICP as in training
(`model.training.train.taught_transform`), its rotation error against the pair's motion, and
the share of source points within 0.01 / 0.05 / 0.1 / 0.2 point spacings of a target point. Then,
for each spacing, how many pairs would teach (share >= MIN_COINCIDENT_SHARE) and the worst error
among them.

    PYTHONPATH=. python docs/training/experiments/teacher_share.py \\
        model/weights/ifnet-fast.pt model/weights/ifnet-indoor.pt
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from model.geometry import apply_transform, rotation_angle_deg
from model.training.scenes import PROTOCOLS, ScanPairs, load_scans
from model.training.train import MIN_COINCIDENT_SHARE, coincident_share, load_teacher, taught_transform

SPACINGS = (0.01, 0.05, 0.1, 0.2)


def polished(teacher: torch.nn.Module, batch: dict[str, torch.Tensor]) -> list[tuple[float, list[float]]]:
    """(rotation error in degrees, share within each of SPACINGS) per pair of the batch."""
    rotations, translations, _ = (poses.double().numpy() for poses in taught_transform(teacher, batch, "cpu", True))
    rows = []
    for i, (rotation, translation) in enumerate(zip(rotations, translations, strict=True)):
        source = batch["noise_free_source"][i].double().numpy()
        target = batch["noise_free_target"][i].double().numpy()
        moved = apply_transform(source, rotation, translation)
        error = float(rotation_angle_deg(rotation, batch["rotation"][i].double().numpy()))
        rows.append((error, [coincident_share(moved, target, spacings) for spacings in SPACINGS]))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("teachers", type=Path, nargs="+", help="weights files")
    parser.add_argument("--domain", default="indoor", choices=sorted(PROTOCOLS))
    parser.add_argument("--pairs", type=int, default=48)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(2)
    scans = list(load_scans(args.domain, "train").values())
    pairs = ScanPairs(scans, PROTOCOLS[args.domain], 768, seed=args.seed)
    batches = [batch for _, batch in zip(range(-(-args.pairs // 8)), DataLoader(pairs, batch_size=8), strict=False)]
    for path in args.teachers:
        teacher = load_teacher(path, "cpu").eval()
        rows = sorted(row for batch in batches for row in polished(teacher, batch))[: args.pairs]
        print(f"{path}: {len(rows)} pairs; polished rotation error median {np.median([e for e, _ in rows]):.3f} deg")
        print("  error (deg) and share within " + " / ".join(f"{s:g}" for s in SPACINGS) + " spacings, per pair:")
        for error, shares in rows:
            print(f"  {error:8.3f}  " + "  ".join(f"{share:.3f}" for share in shares))
        for column, spacing in enumerate(SPACINGS):
            taught = [error for error, shares in rows if shares[column] >= MIN_COINCIDENT_SHARE]
            worst = f", worst {max(taught):.3f} deg" if taught else ""
            print(f"  within {spacing:g} spacings: {len(taught)} of {len(rows)} pairs teach{worst}")


if __name__ == "__main__":
    main()
