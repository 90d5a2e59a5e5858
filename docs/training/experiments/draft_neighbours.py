"""A model repository like service/models/ whose object draft takes fewer EdgeConv neighbours: the
same weights over the draft's one block on 384 points, each point's features max-pooled over `k`
neighbours instead of the 16 they were trained with (its kNN graph narrows with it), exported and
checked against torch as `python -m export` checks. The other files are linked from service/models/.

    PYTHONPATH=. python docs/training/experiments/draft_neighbours.py --neighbours 8 --out /tmp/repo-k8
    python -m bench.ab --sets same:jitter:so3:100 --variant now= --variant 'k8=settings.model_repository="/tmp/repo-k8"'
"""

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

from export.onnx_export import DYNAMIC_AXES, RegistrationGraph, compare_with_torch, export_onnx, metadata_for
from model.artifacts import DEFAULT_WEIGHTS, ort_session
from model.checkpoint import load_checkpoint
from model.ifnet import IFNet
from model.training.data import evaluation_pairs
from service.engine import DRAFTS

SERVED = Path("service/models")
DRAFT_POINTS = 384


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--neighbours", type=int, required=True, help="EdgeConv neighbours of the object draft")
    p.add_argument("--out", type=Path, required=True, help="the repository folder to make")
    args = p.parse_args()
    shipped = load_checkpoint(DEFAULT_WEIGHTS, iterations=1, time_steps=1, num_points=DRAFT_POINTS)
    model = IFNet(replace(shipped.model.config, edgeconv_k=args.neighbours))  # the neighbours are no weight
    model.load_state_dict(shipped.model.state_dict())
    model.eval()
    (args.out / DRAFTS).mkdir(parents=True, exist_ok=True)
    for served in [*SERVED.glob("*.onnx"), *(SERVED / DRAFTS).glob("*.onnx")]:
        link = args.out / served.relative_to(SERVED)
        link.unlink(missing_ok=True)
        link.symlink_to(served.resolve())
    draft = args.out / DRAFTS / "object.onnx"
    draft.unlink()
    example = (torch.rand(1, DRAFT_POINTS, 3) - 0.5, torch.rand(1, DRAFT_POINTS, 3) - 0.5)
    with tempfile.TemporaryDirectory() as tmp:
        candidate = Path(tmp) / "draft.onnx"
        metadata = metadata_for(model, shipped.preset, shipped.sha256)
        export_onnx(RegistrationGraph(model), candidate, example, ["source", "target"], ["rotation", "translation"],
                    DYNAMIC_AXES, metadata)  # fmt: skip
        report = compare_with_torch(ort_session(candidate), model, evaluation_pairs(8))
        print(f"parity on {report.pairs} pairs: max |dR| {report.max_rotation_entry:.1e}")
        if not report.passes(1e-3, 1e-3, 0.01):  # python -m export's default tolerances
            raise SystemExit("ONNX Runtime disagrees with torch: no draft written")
        candidate.replace(draft)
    print(f"wrote {args.out}: the object draft over {args.neighbours} neighbours, the rest linked")


if __name__ == "__main__":
    main()
