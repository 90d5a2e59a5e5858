"""Evaluate a trained IFNet by the paper's protocol, against Open3D baselines on the same pairs.

    python -m model.training.evaluate                          # shipped ONNX model, every set -> docs/evaluation
    python -m model.training.evaluate --model runs/fast/checkpoint.pt --limit 50   # -> runs/evaluation

Sets: same (ModelNet10 test), unseen (ModelNet40 categories absent from ModelNet10), outliers
and jitter (ModelNet10 test with the protocol's two noise variants). Rows: the network alone,
the network + point-to-point ICP (the refinement the service offers), and, when Open3D is
installed, Open3D ICP from identity and FPFH + RANSAC + ICP. Writes <out>/evaluation.md,
evaluation.json and one error histogram PNG per set.
"""

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

# Idle OpenMP threads (torch, Open3D, small_gicp) would otherwise spin for a while after each
# call and steal the CPUs from the next method, skewing every time per pair after the first.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from model.cli import UserError, non_negative_float, non_negative_int, positive_int, reports_user_errors
from model.geometry import at_most, from_matrix, refine, registration_errors, summarise_errors
from model.training.data import DEFAULT_DATA_DIR, Protocol, load_split, make_pair

# Correspondence distance of every ICP here, in unit-sphere units: large enough to pull in a
# few-degree error, small enough that partial overlap does not bias the fit.
ICP_DISTANCE = 0.05
# RANSAC of the FPFH baseline: generous, so that the baseline is not held back by its search.
RANSAC_ITERATIONS, RANSAC_CONFIDENCE = 1_000_000, 0.9999
SETS = {
    "same": ("same", "clean"),
    "unseen": ("unseen", "clean"),
    "outliers": ("same", "outliers"),
    "jitter": ("same", "jitter"),
}
Registration = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
REFINED = "IFNet + ICP"  # the network's estimate refined by point-to-point ICP, as the service offers


def network_runner(model_path: Path, threads: int) -> Registration:
    """(source, target) -> (R, t) with the network, from an ONNX file or a torch checkpoint; clouds
    larger than the network's point count are farthest-point sampled down to it, as the service does."""
    if not model_path.is_file():
        raise UserError(f"--model {model_path}: no such file (an .onnx export or .pt weights)")
    if model_path.suffix == ".onnx":
        from model.artifacts import network_points, ort_session

        try:
            session = ort_session(model_path, threads)
        except Exception as error:  # onnxruntime's own exception types
            raise UserError(f"--model {model_path}: ONNX Runtime cannot load it ({str(error)[:120]})") from None

        points = network_points(session)

        def run_onnx(source: np.ndarray, target: np.ndarray):
            source, target = at_most(source, points), at_most(target, points)
            rotation, translation = session.run(None, {"source": source[None], "target": target[None]})
            return rotation[0].astype(np.float64), translation[0].astype(np.float64)

        return run_onnx

    import torch

    from model.checkpoint import load_checkpoint

    torch.set_num_threads(threads)
    model = load_checkpoint(model_path).model

    def run_torch(source: np.ndarray, target: np.ndarray):
        source, target = at_most(source, model.config.num_points), at_most(target, model.config.num_points)
        with torch.no_grad():
            out = model(torch.from_numpy(source)[None], torch.from_numpy(target)[None])
        return out.rotation[0].double().numpy(), out.translation[0].double().numpy()

    return run_torch


def open3d_baselines() -> dict[str, Registration]:
    """Open3D point-to-point ICP from identity and FPFH + RANSAC + ICP; empty if not installed."""
    try:
        import open3d as o3d
    except ImportError as error:  # includes the missing libusb-1.0-0 case
        print(
            f"Open3D baselines skipped: cannot import open3d ({error}). "
            "Install open3d-cpu and Debian's libusb-1.0-0 to include them."
        )
        return {}
    reg = o3d.pipelines.registration
    voxel = 0.05

    def cloud(points: np.ndarray):
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))

    def icp(source: np.ndarray, target: np.ndarray):
        result = reg.registration_icp(
            cloud(source),
            cloud(target),
            ICP_DISTANCE * 2,
            np.eye(4),
            reg.TransformationEstimationPointToPoint(),
            reg.ICPConvergenceCriteria(max_iteration=50),
        )
        return from_matrix(np.asarray(result.transformation))

    def features(points: np.ndarray):
        pcd = cloud(points).voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        return pcd, reg.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))

    def fpfh_ransac_icp(source: np.ndarray, target: np.ndarray):
        (src, src_f), (tgt, tgt_f) = features(source), features(target)
        coarse = reg.registration_ransac_based_on_feature_matching(
            src,
            tgt,
            src_f,
            tgt_f,
            True,
            1.5 * voxel,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE),
        )
        # The same ICP as the "IFNet + ICP" row, so the two rows differ only in the coarse step.
        coarse_rotation, coarse_translation = from_matrix(np.asarray(coarse.transformation))
        rotation, translation, _ = refine(source, target, coarse_rotation, coarse_translation, ICP_DISTANCE, "ICP")
        return rotation, translation

    o3d.utility.random.seed(0)
    return {"Open3D ICP (identity init)": icp, "FPFH + RANSAC (Open3D) + ICP": fpfh_ransac_icp}


def evaluate_methods(
    methods: dict[str, Registration], pairs: list[dict]
) -> dict[str, tuple[dict[str, float], np.ndarray]]:
    """Summary and per-pair rotation errors of every method, plus "IFNet + ICP".

    Methods run interleaved, pair by pair, so that a change in the machine's speed during the
    run affects them all alike. "IFNet + ICP" refines IFNet's estimate of the same pair; its
    time is IFNet's plus the ICP's.
    """
    runs: dict[str, list[tuple[np.ndarray, np.ndarray, float]]] = {"IFNet": [], REFINED: []}
    runs |= {name: [] for name in methods if name not in runs}
    for pair in pairs:
        source, target = pair["source"], pair["target"]
        for name, register in methods.items():
            started = time.perf_counter()
            rotation, translation = register(source, target)
            runs[name].append((rotation, translation, time.perf_counter() - started))
        rotation, translation, network_seconds = runs["IFNet"][-1]
        started = time.perf_counter()
        rotation, translation, _ = refine(source, target, rotation, translation, ICP_DISTANCE, "ICP")
        runs[REFINED].append((rotation, translation, network_seconds + time.perf_counter() - started))

    truth_r = np.stack([p["rotation"] for p in pairs]).astype(np.float64)
    truth_t = np.stack([p["translation"] for p in pairs]).astype(np.float64)
    results = {}
    for name, estimates in runs.items():
        rotations, translations, seconds = zip(*estimates, strict=True)
        errors = registration_errors(np.stack(rotations), np.stack(translations), truth_r, truth_t)
        summary = summarise_errors(errors) | {"ms_per_pair": 1000 * float(np.median(seconds)), "pairs": len(pairs)}
        results[name] = summary, errors["rotation_deg"]
    return results


def histogram(path: Path, title: str, errors: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.logspace(-6, 2.5, 60)
    for name, values in errors.items():
        ax.hist(np.clip(values, 1e-6, None), bins=bins, histtype="step", lw=1.5, label=name)
    ax.set_xscale("log")
    ax.set_xlabel("isotropic rotation error (deg)")
    ax.set_ylabel("pairs")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def markdown_report(results: dict[str, dict[str, dict]], header: str) -> str:
    columns = [
        "rmse_r",
        "mae_r",
        "rmse_t",
        "mae_t",
        "iso_r_mean",
        "iso_r_median",
        "iso_t_mean",
        "recall_1deg_001",
        "recall_5deg_005",
        "ms_per_pair",
    ]
    lines = [header, ""]
    for set_name, rows in results.items():
        pairs = next(iter(rows.values()))["pairs"]
        lines += [
            f"### {set_name} ({pairs} pairs)",
            "",
            f"![{set_name}]({set_name}_rotation_errors.png)",
            "",
            "| method | " + " | ".join(columns) + " |",
            "|---" * (len(columns) + 1) + "|",
        ]
        for method, summary in rows.items():
            lines.append(f"| {method} | " + " | ".join(f"{summary[c]:.4g}" for c in columns) + " |")
        lines.append("")
    return "\n".join(lines)


PROG = "python -m model.training.evaluate"
PUBLISHED_REPORT = Path("docs/evaluation")
QUICK_REPORT = Path("runs/evaluation")


def display_path(path: Path) -> str:
    """The path relative to the working directory when it lies under it, so reports stay portable."""
    try:
        return str(path.resolve().relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def shape_indices(total: int, limit: int, spread: bool) -> np.ndarray:
    """The shapes of a set to evaluate: every one, its first `limit`, or `limit` spread evenly over
    it. Pair i stays seeded by its shape's index, so a subset's pairs are the full run's pairs."""
    if not limit or limit >= total:
        return np.arange(total)
    if spread:
        return np.linspace(0, total - 1, limit).round().astype(int)
    return np.arange(limit)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from model.artifacts import SERVED_MODEL

    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--model",
        type=Path,
        default=SERVED_MODEL,
        help=".onnx (ONNX Runtime) or .pt (torch); default: the served one",
    )
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=list(SETS))
    parser.add_argument("--limit", type=non_negative_int, default=0, help="pairs per set (0: every shape)")
    parser.add_argument(
        "--spread",
        action="store_true",
        help="with --limit: take the pairs evenly over the set instead of its first shapes (the splits are "
        "ordered by class, so the first 100 ModelNet10 test shapes are bathtubs and beds only)",
    )
    parser.add_argument("--seed", type=int, default=1234, help="pair i of a set is seeded by (seed, i)")
    parser.add_argument(
        "--jitter-sigma",
        type=non_negative_float,
        default=Protocol.jitter_sigma,
        help=f"of the jitter set (the protocol's {Protocol.jitter_sigma:g})",
    )
    parser.add_argument(
        "--shared-jitter",
        action="store_true",
        help="jitter each shape once before the motion and crops, so both clouds share their noisy points "
        "(a diagnostic: isolates the noise from the loss of exact shared points)",
    )
    parser.add_argument("--threads", type=positive_int, default=2, help="of the network and of Open3D (default: 2)")
    parser.add_argument("--no-baselines", action="store_true", help="skip the Open3D baselines")
    parser.add_argument("--data-dir", type=Path, default=DEFAULT_DATA_DIR, help="folder with the ModelNet .npz files")
    parser.add_argument(
        "--out",
        type=Path,
        help=f"report folder (default: {PUBLISHED_REPORT} for the full default run, {QUICK_REPORT} for any "
        "other, so that quick checks never overwrite the published report)",
    )
    args = parser.parse_args(argv)
    if args.out is None:
        defaults = vars(parser.parse_args([]))
        full_run = all(same_option(value, defaults[name]) for name, value in vars(args).items())
        args.out = PUBLISHED_REPORT if full_run else QUICK_REPORT
    return args


def same_option(value, default) -> bool:
    """Paths count as the same file however they are written (the default model given explicitly)."""
    if isinstance(value, Path) and isinstance(default, Path):
        return value.resolve() == default.resolve()
    return value == default


@reports_user_errors(PROG)
def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    network = network_runner(args.model, args.threads)
    methods = {"IFNet": network}
    if not args.no_baselines:
        methods |= open3d_baselines()
    args.out.mkdir(parents=True, exist_ok=True)

    results: dict[str, dict[str, dict]] = {}
    for set_name in args.sets:
        split, noise = SETS[set_name]
        shapes = load_split(split, args.data_dir)
        shared = args.shared_jitter and noise == "jitter"
        protocol = Protocol(noise=noise, jitter_sigma=args.jitter_sigma, shared_jitter=shared)
        pairs = [
            make_pair(shapes[i], protocol, np.random.default_rng((args.seed, i)))
            for i in shape_indices(len(shapes), args.limit, args.spread)
        ]
        network(pairs[0]["source"], pairs[0]["target"])  # warm-up, kept out of the timings
        results[set_name], errors = {}, {}
        for method, (s, rotation_errors) in evaluate_methods(methods, pairs).items():
            results[set_name][method], errors[method] = s, rotation_errors
            print(
                f"{set_name:9s} {method:28s} MAE(R) {s['mae_r']:.4g} deg  MAE(t) {s['mae_t']:.4g}  "
                f"iso R {s['iso_r_mean']:.4g} deg  recall(1deg,0.01) {s['recall_1deg_001']:.3f}  "
                f"{s['ms_per_pair']:.1f} ms/pair"
            )
        histogram(args.out / f"{set_name}_rotation_errors.png", f"{set_name}: rotation error per pair", errors)

    model = display_path(args.model)
    header = (
        f"## Evaluation of `{model}`\n\nPaper protocol (see `model/training/data.py`), pairs seeded by "
        f"(seed={args.seed}, index); ICP correspondence distance {ICP_DISTANCE} (unit-sphere units), the same "
        f"ICP after IFNet and after FPFH + RANSAC ({RANSAC_ITERATIONS:,} iterations, confidence {RANSAC_CONFIDENCE}); "
        f"times are medians per pair on {args.threads} threads.\n\nCommand: `python -m model.training.evaluate "
        f"--model {model}"
        + (f" --sets {' '.join(args.sets)}" if args.sets != list(SETS) else "")
        + (f" --limit {args.limit}" if args.limit else "")
        + (" --spread" if args.spread and args.limit else "")
        + (f" --jitter-sigma {args.jitter_sigma:g}" if args.jitter_sigma != Protocol.jitter_sigma else "")
        + (" --shared-jitter" if args.shared_jitter else "")
        + (" --no-baselines" if args.no_baselines else "")
        + "`"
    )
    (args.out / "evaluation.md").write_text(markdown_report(results, header))
    (args.out / "evaluation.json").write_text(json.dumps({"model": model, "results": results}, indent=2))
    print(f"wrote {args.out / 'evaluation.md'}")
    return results


if __name__ == "__main__":
    main()
