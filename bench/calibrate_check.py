"""Calibrate the answer check (model.geometry.verify_alignment) on pairs with known truth.

    python -m bench.calibrate_check                   # -> docs/verification.json, .md
    python -m bench.calibrate_check --task refine     # -> docs/refinement.json, .md

Sets: ModelNet10 test by the paper's protocol (clean "same", "jitter" sigma 0.01 per cloud,
"outliers"), ModelNet40 "unseen"; the real pairs with ground truth (indoor_pairs.npz); and
real-scan pairs cut from indoor_scans.npz and lidar_scans.npz as bench.harness.scan_pair cuts
them (two overlapping views, each resampled on its own, the second moved). Candidate answers
per pair: the truth with a little noise, the network's answer (inputs prepared as the service
prepares them), that answer refined, the truth perturbed by 2-90 degrees or by a
translation offset, and poses refined from the truth slid aside or turned 20-180 degrees. Every
wrong answer that gets a verified verdict is then sent to the service (`auto`) as the request's
`init`: the check alone cannot tell a symmetric object's flipped pose from the truth, the
pipeline's other answers must. An answer is right when its rotation error is <= 2 degrees and its
translation error <= 2 % of the cloud's extent (the diagonal of its bounding box). The table
counts, per set, the right answers verified, the wrong answers verified (by the check alone, and
by the verdict a request's answer gets) and what the service answered from the latter (none of
which may be wrong and verified). Every cloud is first cut to the subset the service checks
(service.registration.CHECK_MAX_POINTS).
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import httpx  # noqa: E402
import numpy as np  # noqa: E402

from bench import harness  # noqa: E402
from model.geometry import (  # noqa: E402
    INLIER_SPACINGS,
    MAX_DRIFT_SPACINGS,
    MIN_CONSTRAINT,
    MIN_FITNESS,
    MIN_INLIERS,
    AlignmentClouds,
    apply_transform,
    extent,
    from_matrix,
    point_spacing,
    refine,
    slides,
    subset,
    to_matrix,
    verify_alignment,
)
from service.registration import CHECK_MAX_POINTS, refine_distances, verdicts  # noqa: E402
from service.settings import Settings  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MODELNET_SETS = {
    "same": ("same", "clean"),
    "jitter": ("same", "jitter"),
    "outliers": ("same", "outliers"),
    "unseen": ("unseen", "clean"),
}
# Slides of the truth, in shares of the extent: about the service's own (SLIDE_SHARES) and past them.
SLID_SHARES = (0.05, 0.1, 0.2)
TURNED_DEG = (20.0, 180.0)  # turns of the truth about random axes, refined: where a flipped pose fits


def scan_pairs(archive: str, count: int, seed: int) -> list[harness.Pair]:
    """Pairs cut from `count` scans, chosen round-robin over scenes (many scans share a site)."""
    with np.load(harness.DATA / f"{archive}.npz") as data:
        by_scene: dict[str, list[str]] = {}
        for name in sorted(data.keys()):
            by_scene.setdefault(name.split("__")[1], []).append(name)
    rounds = range(max(map(len, by_scene.values())))
    order = [scans[i] for i in rounds for scans in by_scene.values() if i < len(scans)]
    return [harness.scan_pair(f"{archive}/{name}", seed) for name in order[:count]]


def is_right(pair: harness.Pair, rotation: np.ndarray, translation: np.ndarray) -> tuple[bool, float, float]:
    found = harness.errors(pair, rotation, translation)
    return found["right"], found["rotation_deg"], found["translation"] / pair.extent


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
    pair: harness.Pair, network: harness.Network, rng: np.random.Generator, perturbations: int, spacing: float
) -> list[tuple]:
    """(kind, R, t, seconds) answers to score: truth + noise, network, network refined, perturbed."""
    source, target = pair.source, pair.target
    truth = to_matrix(pair.rotation, pair.translation)
    size = extent(target)
    centre = apply_transform(source, pair.rotation, pair.translation).mean(axis=0)
    radius = np.linalg.norm(source - source.mean(axis=0), axis=1).max()
    # The truth within what a converged refinement reaches: points move at most ~half a spacing.
    angle = min(0.5, np.degrees(0.5 * spacing / radius))
    small = about_point(axis_angle(random_axis(rng), rng.uniform(0.0, angle)), centre)
    small[:3, 3] += random_axis(rng) * rng.uniform(0.0, 0.25 * spacing)
    out = [("truth+noise", *from_matrix(small @ truth), 0.0)]
    turned = from_matrix(about_point(axis_angle(random_axis(rng), 5.0), centre) @ truth)
    out.append(("truth+5deg refined", *refine(source, target, *turned, spacing=spacing)[:2], 0.0))
    started = time.perf_counter()
    rotation, translation, normalisation = network.answer(pair)
    network_seconds = time.perf_counter() - started
    out.append(("network", rotation, translation, network_seconds))
    started = time.perf_counter()
    refined = refine(source, target, rotation, translation, spacing=spacing)
    out.append(("refined", refined[0], refined[1], network_seconds + time.perf_counter() - started))
    for _ in range(perturbations):
        angle = float(np.exp(rng.uniform(np.log(2.0), np.log(90.0))))
        out.append(("rotated", *from_matrix(about_point(axis_angle(random_axis(rng), angle), centre) @ truth), 0.0))
    offset = truth.copy()
    offset[:3, 3] += random_axis(rng) * rng.uniform(1.25, 10.0) * harness.RIGHT_TRANSLATION_SHARE * size
    out.append(("shifted", *from_matrix(offset), 0.0))
    clouds = AlignmentClouds(source, target, spacing)
    slid = [(pair.rotation, moved) for moved in slides(pair.translation, target, SLID_SHARES)]
    out += refined_poses(clouds, slid, normalisation.scale, "slid refined")
    turns = [about_point(axis_angle(random_axis(rng), rng.uniform(*TURNED_DEG)), centre) for _ in range(perturbations)]
    out += refined_poses(clouds, [from_matrix(turn @ truth) for turn in turns], normalisation.scale, "turned refined")
    return out


def refined_poses(clouds: AlignmentClouds, poses: list[tuple], scale: float, kind: str) -> list[tuple]:
    """Each pose refined coarse to fine as the service refines: where the truth slid along a long or
    flat scene, or turned on a symmetric object, settles on a wrong pose that fits again."""
    out = []
    for rotation, translation in poses:
        for distance in refine_distances(clouds.spacing, scale):
            rotation, translation, _ = clouds.refine(rotation, translation, distance)
        out.append((kind, rotation, translation, 0.0))
    return out


def given_as_init(client: httpx.Client, pair: harness.Pair, rotation: np.ndarray, translation: np.ndarray) -> str:
    """What `auto` answers when a wrong pose is the request's `init`: "right", "flagged" (wrong, not
    verified) or "wrong verified"."""
    options = {"method": "auto", "refine": True, "init": to_matrix(rotation, translation).tolist()}
    response = client.post(
        "/register",
        params={"options": json.dumps(options)},
        content=harness.npz_body(pair.source, pair.target),
        headers={"content-type": "application/x-npz"},
    )
    response.raise_for_status()
    answer = response.json()
    if is_right(pair, np.array(answer["rotation"]), np.array(answer["translation"]))[0]:
        return "right"
    return "wrong verified" if answer["verified"] else "flagged"


# ---------------------------------------------------------------- run


def evaluate(
    sets: dict[str, list[harness.Pair]], network: harness.Network, perturbations: int, seed: int, client: httpx.Client
) -> list[dict]:
    rows, settings = [], Settings()
    for set_name, pairs in sets.items():
        started = time.perf_counter()
        for index, pair in enumerate(pairs):
            rng = np.random.default_rng((seed, index, 7))
            spacing = max(point_spacing(pair.source), point_spacing(pair.target))
            found = candidates(pair, network, rng, perturbations, spacing)
            poses = [(rotation, translation) for _, rotation, translation, _ in found]
            answers = verdicts(pair.source, pair.target, poses, settings)
            for (kind, rotation, translation, seconds), answer in zip(found, answers):
                right, rotation_error, translation_share = is_right(pair, rotation, translation)
                verdict = verify_alignment(pair.source, pair.target, rotation, translation, spacing)
                fooled = answer.verified and not right
                rows.append(
                    {
                        "set": set_name,
                        "pair": index,
                        "kind": kind,
                        "right": right,
                        "rotation_error_deg": rotation_error,
                        "translation_error_share": translation_share,
                        "verified": verdict.verified,
                        "answer_verified": answer.verified,  # the service's verdict: the check, then the slide check
                        "as_init": given_as_init(client, pair, rotation, translation) if fooled else None,
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


def compare_refinement(sets: dict[str, list[harness.Pair]], network: harness.Network, seed: int) -> list[dict]:
    """Every refinement from the network's answer (and, on real scans, from the truth turned 5
    degrees, since cut views are often beyond the network), methods interleaved pair by pair."""
    methods = refinement_methods()
    results = []
    for set_name, pairs in sets.items():
        starts_from = ["network"] + (["truth+5deg"] if set_name not in MODELNET_SETS else [])
        errors = {(start, name): [] for start in starts_from for name in ["none", *methods]}
        for index, pair in enumerate(pairs):
            source, target = pair.source, pair.target
            rng = np.random.default_rng((seed, index, 11))
            started = time.perf_counter()
            rotation, translation, normalisation = network.answer(pair)
            network_ms = 1000 * (time.perf_counter() - started)
            centre = apply_transform(source, pair.rotation, pair.translation).mean(axis=0)
            turned = about_point(axis_angle(random_axis(rng), 5.0), centre) @ to_matrix(pair.rotation, pair.translation)
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
            right = (rotation_errors <= harness.RIGHT_ROTATION_DEG) & (
                translation_shares <= harness.RIGHT_TRANSLATION_SHARE
            )
            results.append(
                {
                    "set": set_name,
                    "start": start,
                    "method": name,
                    "pairs": len(values),
                    "recall_1deg": float(np.mean(rotation_errors <= 1.0)),
                    "recall_right": float(np.mean(right)),
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


KINDS = ("truth+noise", "network", "refined", "truth+5deg refined", "slid refined")  # right answers verified, by kind
AS_INIT = ("right", "flagged", "wrong verified")


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
            "slid_wrong_verified": sum(row["verified"] for row in wrong if row["kind"] == "slid refined"),
            "turned_wrong_verified": sum(row["verified"] for row in wrong if row["kind"] == "turned refined"),
            "right_answer_verified": sum(row["answer_verified"] for row in right),
            "wrong_answer_verified": sum(row["answer_verified"] for row in wrong),
            **{f"as_init_{outcome}": sum(row["as_init"] == outcome for row in wrong) for outcome in AS_INIT},
        }
        for kind in KINDS:
            kind_right = [row for row in right if row["kind"] == kind]
            entry[f"{kind}_right_verified"] = f"{sum(row['verified'] for row in kind_right)}/{len(kind_right)}"
        summary.append(entry)
    return summary


def rmse_shares(rows: list[dict]) -> dict:
    """How far from the surfaces the inliers of verified answers lie, per set: their RMSE as a share of
    the inlier distance, right and wrong, and the wrong ones above the largest of any right one."""

    def share(row: dict) -> float:
        return row["inlier_rmse"] / row["threshold"]

    verified = [row for row in rows if row["verified"]]
    largest_right = max((share(row) for row in verified if row["right"]), default=0.0)
    per_set = {}
    for set_name in dict.fromkeys(row["set"] for row in rows):
        mine = [row for row in verified if row["set"] == set_name]
        right, wrong = ([share(row) for row in mine if row["right"] == kind] for kind in (True, False))
        per_set[set_name] = {
            "right": [float(np.median(right)), max(right)] if right else None,
            "wrong": [min(wrong), float(np.median(wrong))] if wrong else None,
            "wrong_above": sum(value > largest_right for value in wrong),
            "wrong_verified": len(wrong),
        }
    return {"largest_right": largest_right, "sets": per_set}


def rmse_markdown(shares: dict) -> list[str]:
    """The table of rmse_shares."""
    lines = [
        "",
        "Inlier RMSE as a share of the inlier distance, of the answers the check verifies (a right answer's "
        "inliers lie within the sampling gap and the noise, a wrong pose's anywhere within the distance; not "
        f"a rule of the check). Last column: wrong ones above the largest of any right one "
        f"({shares['largest_right']:.3f}).",
        "",
        "| set | right verified: median / max | wrong verified: min / median | wrong verified above it |",
        "|---|---:|---:|---:|",
    ]
    for set_name, row in shares["sets"].items():
        right, wrong = (f"{row[kind][0]:.3f} / {row[kind][1]:.3f}" if row[kind] else "-" for kind in ("right", "wrong"))
        lines.append(f"| {set_name} | {right} | {wrong} | {row['wrong_above']} / {row['wrong_verified']} |")
    return lines


def markdown(summary: list[dict], shares: dict, command: str, seconds: float) -> str:
    lines = [
        "# Verification check: calibration",
        "",
        f"`{command}` ({seconds / 60:.1f} min on the 2-core build machine). Right: rotation error <= 2 deg and "
        "translation error <= 2 % of the target's bounding-box diagonal. Candidates per pair: the truth moved "
        "by at most half a point spacing (truth+noise), the network's answer as the service computes it, that "
        "answer refined (model.geometry.refine), the truth turned 5 deg and refined, the truth turned 2-90 deg "
        "(log-uniform) about the overlap's centre, the truth shifted by 2.5-20 % of the extent, the truth "
        f"slid by {', '.join(f'{share:.0%}' for share in SLID_SHARES)} of the extent both ways along each "
        "principal axis of the target and refined coarse to fine as the service refines (slid refined), and "
        f"the truth turned {TURNED_DEG[0]:.0f}-{TURNED_DEG[1]:.0f} deg (uniform) about random axes through "
        "the overlap's centre and refined alike (turned refined). "
        '"Check": the check alone; "answer": the '
        "verdict a request's answer gets (service.registration.verdicts: the check, then the slide check, "
        "which looks beside a verified answer matching little of the source unless feature matching's guess "
        "lands on it, as under `auto`). Neither judges a flipped pose "
        "of a symmetric object: the pipeline does, by its other answers (feature matching, the rotated "
        "starts, the half turns). So every wrong answer with a verified verdict is sent to the service "
        "(`auto`, `refine`) as the request's `init`, the network starting from it: what the service answers "
        'is the last columns\' count ("as init"). Last columns: right answers the check verified, by kind.',
        "",
        f"The rule (model.geometry.judge): at least {MIN_INLIERS} source points within {INLIER_SPACINGS} point "
        f"spacings of the target, fitness and reverse overlap >= {MIN_FITNESS}, inlier constraint >= "
        f"{MIN_CONSTRAINT} (the matching points pin all six motions down) and a drift <= {MAX_DRIFT_SPACINGS} "
        "spacings when refine() (GICP) refines the answer once (a right answer has settled).",
        "",
        "| set | pairs | right verified: check | answer | wrong verified: check | of which slid refined | "
        "turned refined | answer | as init: right / flagged | **as init: wrong verified** | "
        + " | ".join(KINDS)
        + " |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * len(KINDS),
    ]
    for row in summary:
        kinds = " | ".join(row[f"{kind}_right_verified"] for kind in KINDS)
        lines.append(
            f"| {row['set']} | {row['pairs']} | {row['right_verified']} / {row['right']} | "
            f"{row['right_answer_verified']} | {row['wrong_verified']} / {row['wrong']} | "
            f"{row['slid_wrong_verified']} | {row['turned_wrong_verified']} | {row['wrong_answer_verified']} | "
            f"{row['as_init_right']} / {row['as_init_flagged']} | **{row['as_init_wrong verified']}** | {kinds} |"
        )
    return "\n".join(lines + rmse_markdown(shares)) + "\n"


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
    parser.add_argument("--model", type=Path, default=REPO / "service" / "models" / "object.onnx")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "verification")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    network = harness.Network(args.model, args.threads)
    sets = {}
    for name in args.sets:
        if name in MODELNET_SETS:
            sets[name] = harness.modelnet_pairs(args.pairs, *MODELNET_SETS[name], seed=args.seed)
        elif name == "indoor_pairs":
            sets[name] = harness.truth_pairs()
        else:
            sets[name] = scan_pairs(name, args.scans, args.seed)
    for pairs in sets.values():  # the clouds the service checks: at most CHECK_MAX_POINTS of each
        for pair in pairs:
            pair.source, pair.target = subset(pair.source, CHECK_MAX_POINTS), subset(pair.target, CHECK_MAX_POINTS)
    command = "python -m bench.calibrate_check " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.task == "refine":
        results = compare_refinement(sets, network, args.seed)
        seconds = time.perf_counter() - started
        text = refinement_markdown(results, command.strip(), seconds)
        print(text)
        write(args.out.with_name("refinement"), text, {"command": command, "seconds": seconds, "results": results})
        return
    with harness.Service() as service, httpx.Client(base_url=service.url, timeout=600, trust_env=False) as client:
        rows = evaluate(sets, network, args.perturbations, args.seed, client)
    summary, shares = table(rows), rmse_shares(rows)
    seconds = time.perf_counter() - started
    text = markdown(summary, shares, command.strip(), seconds)
    print(text)
    write(args.out, text, {"command": command, "seconds": seconds, "sets": summary, "rmse_shares": shares})


def write(stem: Path, text: str, data: dict) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".md").write_text(text)
    stem.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n")


if __name__ == "__main__":
    main()
