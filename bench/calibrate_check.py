"""Calibrate the answer check (model.geometry.verify_alignment) on pairs with known truth.

    PYTHONPATH=$PWD python bench/calibrate_check.py            # -> docs/verification.json, .md

Sets: ModelNet10 test by the paper's protocol (clean "same", "jitter" sigma 0.01 per cloud,
"outliers"), ModelNet40 "unseen"; the real pairs with ground truth (indoor_pairs.npz); and
real-scan pairs cut from indoor_scans.npz and lidar_scans.npz: two disjoint random halves of a
scan (so the views share no exact point), each cropped to a view from its own direction, the
second moved by the protocol's motion. Candidate answers per pair: the truth with a little noise,
the network's answer (inputs prepared as the service prepares them), that answer refined, and
the truth perturbed by 2-90 degrees or by a translation offset. An answer is right when its
rotation error is <= 2 degrees and its translation error <= 2 % of the target's extent (the
diagonal of its bounding box). The table counts, per set, the right answers the check verified
and the wrong answers it verified (the latter must be zero).
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from model.geometry import (  # noqa: E402
    INLIER_SPACINGS,
    MAX_DRIFT_SPACINGS,
    MIN_CONSTRAINT,
    MIN_FITNESS,
    MIN_INLIERS,
    NETWORK_RADIUS,
    Normalisation,
    apply_transform,
    crop_nearest,
    disjoint_halves,
    from_matrix,
    nearest_rotation,
    point_spacing,
    random_rotation,
    refine,
    remove_duplicates,
    resample_indices,
    rotation_angle_deg,
    to_matrix,
    verify_alignment,
)
from model.training.data import DEFAULT_DATA_DIR, Protocol, load_split, make_pair  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RIGHT_ROTATION_DEG = 2.0
RIGHT_TRANSLATION_SHARE = 0.02  # of the target's bounding-box diagonal
MODELNET_SETS = {
    "same": ("same", "clean"),
    "jitter": ("same", "jitter"),
    "outliers": ("same", "outliers"),
    "unseen": ("unseen", "clean"),
}
NETWORK_POINTS = 768
FPS_MAX_INPUT = 32_768  # the service's default fps_max_input_points


# ---------------------------------------------------------------- the network, as the service runs it


def sample_indices(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """service.registration.sample_indices with the service's defaults (fps, seed 0)."""
    rng = np.random.default_rng(seed)
    if len(points) > FPS_MAX_INPUT:
        subset = np.sort(rng.choice(len(points), size=FPS_MAX_INPUT, replace=False))
        return subset[resample_indices(FPS_MAX_INPUT, count, "fps", rng, points[subset])]
    return resample_indices(len(points), count, "fps", rng, points)


class Network:
    def __init__(self, model_path: Path, threads: int):
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        self.session = ort.InferenceSession(str(model_path), options, providers=["CPUExecutionProvider"])

    def prepare(self, source: np.ndarray, target: np.ndarray):
        """The service's _prepare: distinct points, resampled to the network's count, normalised."""
        source_sampled = source[sample_indices(source, NETWORK_POINTS)]
        target_sampled = target[sample_indices(target, NETWORK_POINTS)]
        normalisation = Normalisation(source_sampled, target_sampled)
        return (
            normalisation.source(source_sampled).astype(np.float32),
            normalisation.target(target_sampled).astype(np.float32),
            normalisation,
        )

    def run_batch(self, sources: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rotation, translation = self.session.run(None, {"source": sources, "target": targets})
        return rotation.astype(np.float64), translation.astype(np.float64)

    def register(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, Normalisation]:
        """(R, t) in user units, as the service's _finish maps the network's answer back."""
        source_n, target_n, normalisation = self.prepare(source, target)
        rotation, translation = self.run_batch(source_n[None], target_n[None])
        rotation, translation = normalisation.to_user_units(nearest_rotation(rotation[0]), translation[0])
        return rotation, translation, normalisation


# ---------------------------------------------------------------- pairs


def modelnet_pairs(name: str, count: int, seed: int) -> list[dict]:
    split, noise = MODELNET_SETS[name]
    shapes = load_split(split)
    chosen = np.random.default_rng(seed).choice(len(shapes), size=min(count, len(shapes)), replace=False)
    protocol = Protocol(noise=noise)
    pairs = []
    for i in np.sort(chosen):
        pair = make_pair(shapes[i], protocol, np.random.default_rng((seed, int(i))))
        pairs.append({key: pair[key].astype(np.float64) for key in ("source", "target", "rotation", "translation")})
    return pairs


def indoor_pairs(data_dir: Path) -> list[dict]:
    with np.load(data_dir / "indoor_pairs.npz") as archive:
        names = sorted({key.split("/")[0] for key in archive})
        return [
            {
                "source": archive[f"{n}/source"].astype(np.float64),
                "target": archive[f"{n}/target"].astype(np.float64),
                "rotation": archive[f"{n}/T"][:3, :3].astype(np.float64),
                "translation": archive[f"{n}/T"][:3, 3].astype(np.float64),
                "name": n,
            }
            for n in names
        ]


def two_views(scan: np.ndarray, rng: np.random.Generator, keep: float = 0.7) -> tuple[np.ndarray, np.ndarray]:
    """Two views of one scan that share no exact point: disjoint random halves, each cropped to
    `keep` of its points nearest a far anchor; the anchors lie 40-90 degrees apart in the scan's
    principal plane (rooms and lidar sweeps are wide and flat), so the views overlap in part."""
    first, second = disjoint_halves(scan, rng)
    centre = scan.mean(axis=0)
    _, _, axes = np.linalg.svd(scan - centre, full_matrices=False)
    far = 100.0 * np.abs(scan - centre).max()
    angle = rng.uniform(0, 2 * np.pi)
    views = []
    for points, theta in ((first, angle), (second, angle + np.radians(rng.uniform(40, 90)))):
        anchor = centre + far * (np.cos(theta) * axes[0] + np.sin(theta) * axes[1])
        views.append(crop_nearest(points, anchor, int(keep * len(points))))
    return views[0], views[1]


def scan_pairs(path: Path, count: int, seed: int) -> list[dict]:
    """Pairs cut from `count` scans, chosen round-robin over scenes (many scans share a site)."""
    with np.load(path) as archive:
        names = sorted(archive.keys())
        by_scene: dict[str, list[str]] = {}
        for name in names:
            by_scene.setdefault(name.split("__")[1], []).append(name)
        order = [
            scans[i] for i in range(max(map(len, by_scene.values()))) for scans in by_scene.values() if i < len(scans)
        ]
        pairs = []
        for index, name in enumerate(order[:count]):
            rng = np.random.default_rng((seed, index))
            scan = remove_duplicates(archive[name].astype(np.float64))
            source, view = two_views(scan, rng)
            radius = np.linalg.norm(scan - scan.mean(axis=0), axis=1).max() / NETWORK_RADIUS
            rotation, _ = random_rotation(rng)
            translation = rng.uniform(-0.5, 0.5, size=3) * radius
            target = apply_transform(view, rotation, translation)
            pairs.append(
                {"source": source, "target": target, "rotation": rotation, "translation": translation, "name": name}
            )
    return pairs


# ---------------------------------------------------------------- candidates


def random_axis(rng: np.random.Generator) -> np.ndarray:
    axis = rng.normal(size=3)
    return axis / np.linalg.norm(axis)


def axis_angle(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis * np.radians(angle_deg)).as_matrix()


def about_point(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """4x4 of a rotation about `centre`."""
    return to_matrix(rotation, centre - rotation @ centre)


def candidates(
    pair: dict, network: Network, rng: np.random.Generator, perturbations: int, spacing: float
) -> list[tuple]:
    """(kind, R, t, seconds) answers to score: truth + noise, network, network refined, perturbed."""
    source, target = pair["source"], pair["target"]
    truth = to_matrix(pair["rotation"], pair["translation"])
    extent = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0)))
    centre = apply_transform(source, pair["rotation"], pair["translation"]).mean(axis=0)
    radius = np.linalg.norm(source - source.mean(axis=0), axis=1).max()
    # The truth within what a converged refinement reaches: points move at most ~half a spacing.
    angle = min(0.5, np.degrees(0.5 * spacing / radius))
    small = about_point(axis_angle(random_axis(rng), rng.uniform(0.0, angle)), centre)
    small[:3, 3] += random_axis(rng) * rng.uniform(0.0, 0.25 * spacing)
    out = [("truth+noise", *from_matrix(small @ truth), 0.0)]
    turned = from_matrix(about_point(axis_angle(random_axis(rng), 5.0), centre) @ truth)
    out.append(("truth+5deg refined", *refine(source, target, *turned, spacing=spacing)[:2], 0.0))
    started = time.perf_counter()
    rotation, translation, normalisation = network.register(source, target)
    network_seconds = time.perf_counter() - started
    out.append(("network", rotation, translation, network_seconds))
    started = time.perf_counter()
    refined = refine(source, target, rotation, translation, spacing=spacing)
    out.append(("refined", refined[0], refined[1], network_seconds + time.perf_counter() - started))
    for _ in range(perturbations):
        angle = float(np.exp(rng.uniform(np.log(2.0), np.log(90.0))))
        out.append(("rotated", *from_matrix(about_point(axis_angle(random_axis(rng), angle), centre) @ truth), 0.0))
    offset = truth.copy()
    offset[:3, 3] += random_axis(rng) * rng.uniform(1.25, 10.0) * RIGHT_TRANSLATION_SHARE * extent
    out.append(("shifted", *from_matrix(offset), 0.0))
    return out


def is_right(pair: dict, rotation: np.ndarray, translation: np.ndarray) -> tuple[bool, float, float]:
    target = pair["target"]
    extent = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0)))
    rotation_error = float(rotation_angle_deg(rotation, pair["rotation"]))
    translation_share = float(np.linalg.norm(translation - pair["translation"]) / extent)
    return (
        rotation_error <= RIGHT_ROTATION_DEG and translation_share <= RIGHT_TRANSLATION_SHARE,
        rotation_error,
        translation_share,
    )


# ---------------------------------------------------------------- run


def evaluate(sets: dict[str, list[dict]], network: Network, perturbations: int, seed: int) -> list[dict]:
    rows = []
    for set_name, pairs in sets.items():
        started = time.perf_counter()
        for index, pair in enumerate(pairs):
            rng = np.random.default_rng((seed, index, 7))
            spacing = max(point_spacing(pair["source"]), point_spacing(pair["target"]))
            for kind, rotation, translation, seconds in candidates(pair, network, rng, perturbations, spacing):
                right, rotation_error, translation_share = is_right(pair, rotation, translation)
                verdict = verify_alignment(pair["source"], pair["target"], rotation, translation, spacing)
                rows.append(
                    {
                        "set": set_name,
                        "pair": index,
                        "kind": kind,
                        "right": right,
                        "rotation_error_deg": rotation_error,
                        "translation_error_share": translation_share,
                        "verified": verdict.verified,
                        "reason": verdict.reason,
                        "seconds": seconds,
                        "drift": verdict.drift,
                        **verdict.score._asdict(),
                    }
                )
        print(f"{set_name}: {len(pairs)} pairs in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    return rows


# ---------------------------------------------------------------- refinement comparison

DEFAULT_DISTANCE_NORMALISED = 0.05  # service.registration's fixed ICP distance, in normalised units


def refinement_methods() -> dict:
    """name -> (method, distance rule): a number is spacings, "fixed" the service's 0.05 normalised."""
    return {
        "ICP fixed 0.05": ("ICP", "fixed"),
        "ICP 2x spacing": ("ICP", 2.0),
        "ICP 3x spacing": ("ICP", 3.0),
        "PLANE fixed 0.05": ("PLANE_ICP", "fixed"),
        "PLANE 2x spacing": ("PLANE_ICP", 2.0),
        "PLANE 3x spacing": ("PLANE_ICP", 3.0),
        "GICP 2x spacing": ("GICP", 2.0),
        "GICP 3x spacing": ("GICP", 3.0),
    }


def compare_refinement(sets: dict[str, list[dict]], network: Network, seed: int) -> list[dict]:
    """Every refinement from the network's answer (and, on real scans, from the truth turned 5
    degrees, since cut views are often beyond the network), methods interleaved pair by pair."""
    methods = refinement_methods()
    results = []
    for set_name, pairs in sets.items():
        starts_from = ["network"] + (["truth+5deg"] if set_name not in MODELNET_SETS else [])
        errors = {(start, name): [] for start in starts_from for name in ["none", *methods]}
        for index, pair in enumerate(pairs):
            source, target = pair["source"], pair["target"]
            rng = np.random.default_rng((seed, index, 11))
            started = time.perf_counter()
            rotation, translation, normalisation = network.register(source, target)
            network_ms = 1000 * (time.perf_counter() - started)
            centre = apply_transform(source, pair["rotation"], pair["translation"]).mean(axis=0)
            turned = about_point(axis_angle(random_axis(rng), 5.0), centre) @ to_matrix(
                pair["rotation"], pair["translation"]
            )
            starts = {"network": (rotation, translation), "truth+5deg": from_matrix(turned)}
            spacing = max(point_spacing(source), point_spacing(target))
            for start in starts_from:
                rotation0, translation0 = starts[start]
                errors[(start, "none")].append((*is_right(pair, rotation0, translation0)[1:], network_ms))
                for name, (method, rule) in methods.items():
                    distance = DEFAULT_DISTANCE_NORMALISED / normalisation.scale if rule == "fixed" else rule * spacing
                    began = time.perf_counter()
                    refined = refine(source, target, rotation0, translation0, distance, method=method)
                    ms = 1000 * (time.perf_counter() - began)
                    errors[(start, name)].append((*is_right(pair, refined[0], refined[1])[1:], ms))
        for (start, name), values in errors.items():
            rotation_errors, translation_shares, ms = map(np.array, zip(*values))
            results.append(
                {
                    "set": set_name,
                    "start": start,
                    "method": name,
                    "pairs": len(values),
                    "recall_1deg": float(np.mean(rotation_errors <= 1.0)),
                    "recall_right": float(
                        np.mean(
                            (rotation_errors <= RIGHT_ROTATION_DEG) & (translation_shares <= RIGHT_TRANSLATION_SHARE)
                        )
                    ),
                    "median_rotation_deg": float(np.median(rotation_errors)),
                    "median_ms": float(np.median(ms)),
                }
            )
            row = results[-1]
            print(
                f"{set_name:12s} {start:11s} {name:18s} recall@1 {row['recall_1deg']:.3f} right "
                f"{row['recall_right']:.3f} median {row['median_rotation_deg']:.3f} deg {row['median_ms']:.1f} ms",
                file=sys.stderr,
            )
    return results


def table(rows: list[dict]) -> list[dict]:
    summary = []
    for set_name in dict.fromkeys(row["set"] for row in rows):
        mine = [row for row in rows if row["set"] == set_name]
        right = [row for row in mine if row["right"]]
        wrong = [row for row in mine if not row["right"]]
        entry = {
            "set": set_name,
            "pairs": len({row["pair"] for row in mine}),
            "right_verified": sum(row["verified"] for row in right),
            "right": len(right),
            "wrong_verified": sum(row["verified"] for row in wrong),
            "wrong": len(wrong),
        }
        for kind in ("truth+noise", "network", "refined", "truth+5deg refined"):
            kind_right = [row for row in right if row["kind"] == kind]
            entry[f"{kind}_right_verified"] = f"{sum(row['verified'] for row in kind_right)}/{len(kind_right)}"
        summary.append(entry)
    return summary


KINDS = ("truth+noise", "network", "refined", "truth+5deg refined")


def markdown(summary: list[dict], command: str, seconds: float) -> str:
    lines = [
        "# Verification check: calibration",
        "",
        f"`{command}` ({seconds / 60:.1f} min on the 2-core build machine). Right: rotation error <= 2 deg and "
        "translation error <= 2 % of the target's bounding-box diagonal. Candidates per pair: the truth moved "
        "by at most half a point spacing (truth+noise), the network's answer as the service computes it, that "
        "answer refined (model.geometry.refine), the truth turned 5 deg and refined, the truth turned 2-90 deg "
        "(log-uniform) about the overlap's centre, and the truth shifted by 2.5-20 % of the extent. Last columns: "
        "right answers verified by kind.",
        "",
        f"The rule (model.geometry.judge): at least {MIN_INLIERS} source points within {INLIER_SPACINGS} point "
        f"spacings of the target, fitness and reverse overlap >= {MIN_FITNESS}, inlier constraint >= "
        f"{MIN_CONSTRAINT} (the matching points pin all six motions down) and a drift <= {MAX_DRIFT_SPACINGS} "
        "spacings when refine() (GICP) refines the answer once (a right answer has settled).",
        "",
        "| set | pairs | right verified | **wrong verified** | " + " | ".join(KINDS) + " |",
        "|---|---:|---:|---:|" + "---:|" * len(KINDS),
    ]
    for row in summary:
        kinds = " | ".join(row[f"{kind}_right_verified"] for kind in KINDS)
        lines.append(
            f"| {row['set']} | {row['pairs']} | {row['right_verified']} / {row['right']} | "
            f"**{row['wrong_verified']}** / {row['wrong']} | {kinds} |"
        )
    return "\n".join(lines) + "\n"


def refinement_markdown(results: list[dict], command: str, seconds: float) -> str:
    lines = [
        "# Refinement from the network's answer",
        "",
        f"`{command}` ({seconds / 60:.1f} min on the 2-core build machine). Recall: share of pairs within 1 degree; "
        "right: within 2 degrees and 2 % of the target's extent; ms: the refinement alone (the `none` row: the "
        "network's call), median.",
        "",
        "| set | start | refinement | pairs | recall at 1 deg | right | median rotation error (deg) | ms |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r['set']} | {r['start']} | {r['method']} | {r['pairs']} | {r['recall_1deg']:.3f} | "
            f"{r['recall_right']:.3f} | {r['median_rotation_deg']:.3f} | {r['median_ms']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", choices=["check", "refine"], default="check")
    parser.add_argument("--pairs", type=int, default=100, help="pairs per ModelNet set")
    parser.add_argument("--scans", type=int, default=40, help="scan pairs per real-scan set")
    parser.add_argument("--perturbations", type=int, default=4, help="rotated wrong answers per pair")
    parser.add_argument("--sets", nargs="+", default=[*MODELNET_SETS, "indoor_pairs", "indoor_scans", "lidar_scans"])
    parser.add_argument("--model", type=Path, default=REPO / "service" / "models" / "ifnet.onnx")
    parser.add_argument("--data-dir", type=Path, default=DEFAULT_DATA_DIR)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "verification")
    parser.add_argument("--rows", type=Path, help="also write every candidate's scores here (.json)")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    network = Network(args.model, args.threads)
    sets = {}
    for name in args.sets:
        if name in MODELNET_SETS:
            sets[name] = modelnet_pairs(name, args.pairs, args.seed)
        elif name == "indoor_pairs":
            sets[name] = indoor_pairs(args.data_dir)
        else:
            sets[name] = scan_pairs(args.data_dir / f"{name}.npz", args.scans, args.seed)
    command = "PYTHONPATH=$PWD python bench/calibrate_check.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.task == "refine":
        results = compare_refinement(sets, network, args.seed)
        seconds = time.perf_counter() - started
        text = refinement_markdown(results, command.strip(), seconds)
        print(text)
        write(args.out.with_name("refinement"), text, {"command": command, "seconds": seconds, "results": results})
        return
    rows = evaluate(sets, network, args.perturbations, args.seed)
    summary = table(rows)
    seconds = time.perf_counter() - started
    text = markdown(summary, command.strip(), seconds)
    print(text)
    write(args.out, text, {"command": command, "seconds": seconds, "sets": summary})
    if args.rows:
        args.rows.write_text(json.dumps(rows))


def write(stem: Path, text: str, data: dict) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".md").write_text(text)
    stem.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n")


if __name__ == "__main__":
    main()
