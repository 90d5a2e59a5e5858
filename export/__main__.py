"""Export trained IFNet weights to ONNX, check the file against torch, and only then write it.

python -m export                                   # shipped weights -> service/models/object.onnx
python -m export --weights runs/fast/checkpoint.pt --output /tmp/ifnet.onnx
python -m export --iterations 6 --output /tmp/ifnet-6.onnx  # 3 time steps x 6 iterations
python -m export --time-steps 2 --iterations 4 --output /tmp/ifnet-2x4.onnx
python -m export --time-steps 1 --iterations 1 --points 384 --output service/models/drafts/object.onnx  # a draft
"""

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import onnx
import torch

from export.onnx_export import DYNAMIC_AXES, RegistrationGraph, compare_with_torch, export_onnx, metadata_for
from model.artifacts import DEFAULT_WEIGHTS, SERVED_MODEL, ort_session
from model.checkpoint import load_checkpoint
from model.cli import UserError, positive_int, reports_user_errors
from model.training.data import evaluation_pairs

PROG = "python -m export"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS, help="checkpoint or shipped weights (.pt)")
    parser.add_argument("--output", type=Path, default=SERVED_MODEL, help="where the checked .onnx goes")
    parser.add_argument(
        "--iterations",
        type=positive_int,
        default=None,
        help="blocks per time step in the exported graph (default: as trained); the block's weights are "
        "shared, so any count runs; measured effect: docs/training/experiments/README.md",
    )
    parser.add_argument(
        "--time-steps",
        type=positive_int,
        default=None,
        help="passes over the iterations, each fed back the last pass's target features (default: as trained)",
    )
    parser.add_argument(
        "--points",
        type=positive_int,
        default=None,
        help="native points per cloud recorded in the metadata, to which the service resamples (default: as trained)",
    )
    parser.add_argument("--preset-name", default=None, help="recorded in the metadata (default: from the weights file)")
    parser.add_argument(
        "--check-pairs", type=positive_int, default=8, help="pairs compared between torch and ONNX Runtime"
    )
    parser.add_argument("--rotation-tol", type=float, default=1e-3, help="max |R_onnx - R_torch| per entry")
    parser.add_argument(
        "--translation-tol", type=float, default=1e-3, help="max |t_onnx - t_torch| per entry (unit-sphere units)"
    )
    parser.add_argument("--angle-tol", type=float, default=0.01, help="max difference of rotation errors (deg)")
    return parser.parse_args(argv)


@reports_user_errors(PROG)
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:  # an unusable --output fails now, not after the export
        args.output.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise UserError(f"--output {args.output}: a file stands where its folder would be") from None
    model, weights_sha256, weights_preset = load_checkpoint(args.weights, args.iterations, args.time_steps, args.points)
    preset_name = args.preset_name or weights_preset
    n = model.config.num_points
    example = (torch.rand(1, n, 3) - 0.5, torch.rand(1, n, 3) - 0.5)

    with tempfile.TemporaryDirectory() as tmp:
        candidate = Path(tmp) / "candidate.onnx"
        seconds = export_onnx(
            RegistrationGraph(model),
            candidate,
            example,
            ["source", "target"],
            ["rotation", "translation"],
            DYNAMIC_AXES,
            metadata_for(model, preset_name, weights_sha256),
        )
        onnx.checker.check_model(str(candidate), full_check=True)
        report = compare_with_torch(ort_session(candidate), model, evaluation_pairs(args.check_pairs))
        print(
            f"exported in {seconds:.1f} s, {candidate.stat().st_size / 1e6:.2f} MB; parity on {report.pairs} pairs: "
            f"max |dR| {report.max_rotation_entry:.2e}, max |dt| {report.max_translation_entry:.2e}, "
            f"max rotation-error difference {report.max_angle_difference_deg:.2e} deg"
        )
        if not report.passes(args.rotation_tol, args.translation_tol, args.angle_tol):
            print(
                f"refusing to write {args.output}: ONNX Runtime disagrees with torch beyond "
                f"|dR| <= {args.rotation_tol}, |dt| <= {args.translation_tol} or {args.angle_tol} deg",
                file=sys.stderr,
            )
            return 1
        shutil.move(candidate, args.output)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
