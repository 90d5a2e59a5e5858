"""The network, the service and the classical peers on the same pairs, interleaved pair by pair.

    python -m bench.compare peers                      # ModelNet10 and real-scan pairs -> docs/benchmarks/compare.json
    python -m bench.compare peers --modelnet same:jitter unseen:clean:so3 --scans lidar_scans/NAME
    python -m bench.compare peers --modelnet --scans --no-truth-pairs --scenes indoor outdoor \
        --request 'indoor={"model": "indoor", "method": "ifnet"}'           # the paper's scene protocols
    python -m bench.compare peers --request auto='{"method": "auto", "refine": true}'   # one more service row
    python -m bench.compare peers --setting two-calls=model_calls=2   # each service row again on another server
    python -m bench.compare peers --modelnet --no-truth-pairs --seed 0-19    # 20 views of each real scan
    python -m bench.compare models service/models/object.onnx /tmp/new.onnx    # ONNX files: time and accuracy
    python -m bench.compare models service/models/object.onnx service/models/drafts/object.onnx --refine \
        --sets same:clean same:jitter same:outliers unseen:clean                # and after refinement

Every method meets every pair, in an order rotated from pair to pair and reversed every other pair;
a method's time is read as its per-pair ratio to each peer (median over the pairs), since the
machine's speed drifts.
"""

import argparse
import contextlib
import dataclasses
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np

from bench import harness
from model.geometry import AlignmentClouds
from service.registration import refine_distances

DEFAULT_REQUESTS = ("service={}", 'service+refine={"refine": true}')
PEERS = ("open3d", "kiss")


def timed(function, *args, **kwargs):
    started = time.perf_counter()
    result = function(*args, **kwargs)
    return result, 1000.0 * (time.perf_counter() - started)


class Methods:
    """Each method maps a pair to {ms, rotation_deg, translation, right, ...}; inputs are prepared untimed."""

    def __init__(self, args, services: dict[str, harness.Service]):
        """`services`: the default server first, then one per `--setting`, whose rows are `REQUEST@SETTING`."""
        self.network = harness.Network(args.model, args.threads)
        clients = {name: httpx.Client(base_url=s.url, timeout=600, trust_env=False) for name, s in services.items()}
        default, *others = clients
        self.requests = {}  # row -> (client, options)
        for name, options in (spec.split("=", 1) for spec in args.request):
            self.requests[name] = (clients[default], options)
            self.requests |= {f"{name}@{setting}": (clients[setting], options) for setting in others}
        self.tight_max_points = args.tight_max_points
        self.names = ["network", *self.requests, *PEERS, "open3d-tight"]

    def run(self, name: str, pair: harness.Pair, prepared: dict) -> dict | None:
        if name == "network":
            feeds, normalisation = prepared["feeds"]
            (rotation, translation), ms = timed(self.network.call, feeds)
            return {"ms": ms, **harness.errors(pair, *self.network.to_user_units(normalisation, rotation, translation))}
        if name in self.requests:
            return self.request(pair, prepared["body"], *self.requests[name])
        if name == "open3d-tight":
            if max(len(pair.source), len(pair.target)) > self.tight_max_points:
                return None
            (rotation, translation), ms = timed(
                harness.open3d_fpfh_ransac_icp, pair.source, pair.target, pair.voxel, True
            )
        else:
            peer = harness.open3d_fpfh_ransac_icp if name == "open3d" else harness.kiss_matcher_gicp
            (rotation, translation), ms = timed(peer, pair.source, pair.target, pair.voxel)
        return {"ms": ms, **harness.errors(pair, rotation, translation)}

    def request(self, pair: harness.Pair, body: bytes, client: httpx.Client, options: str) -> dict:
        headers = {"content-type": "application/x-npz"}
        response, ms = timed(client.post, "/register", params={"options": options}, content=body, headers=headers)
        if response.status_code != 200:
            return {"ms": ms, "status": response.status_code, "right": False, "error": response.text[:300]}
        answer = response.json()
        row = {"ms": ms, "status": 200, **harness.errors(pair, np.array(answer["rotation"]), answer["translation"])}
        row["timings_ms"] = answer.get("timings_ms")
        row |= {key: answer[key] for key in ("verified", "stage", "reason", "fitness") if key in answer}
        return row


def paper_errors(rows: list[dict]) -> dict:
    """The paper's table II columns: MAE and RMSE of the Euler angles (deg) and of the translation."""
    if not rows:
        return {}
    euler, shift = (np.array([row[key] for row in rows]) for key in ("euler_abs_deg", "translation_abs"))
    return {
        "mae_r_deg": float(euler.mean()),
        "rmse_r_deg": float(np.sqrt((euler**2).mean())),
        "mae_t": float(shift.mean()),
        "rmse_t": float(np.sqrt((shift**2).mean())),
    }


def summary(pairs: list[dict], names: list[str]) -> dict:
    result = {}
    for name in names:
        rows = [(pair["results"][name], pair["results"]) for pair in pairs if pair["results"].get(name)]
        if not rows:
            continue
        done = [row for row, _ in rows if "rotation_deg" in row]
        # A row on another server (`REQUEST@SETTING`) is also timed against the same request on the default one.
        bases = [*PEERS, *([name.partition("@")[0]] if "@" in name else [])]
        ratios = {
            base: statistics.median(row["ms"] / others[base]["ms"] for row, others in rows)
            for base in bases
            if all(others.get(base) for _, others in rows)
        }
        result[name] = {
            "pairs": len(rows),
            "recall": sum(row["right"] for row, _ in rows) / len(rows),
            "median_rotation_deg": statistics.median(row["rotation_deg"] for row in done) if done else None,
            "median_translation": statistics.median(row["translation"] for row in done) if done else None,
            "failed_requests": sum(row.get("status", 200) != 200 for row, _ in rows),
            "verified": sum(row.get("verified") is True for row, _ in rows)
            if any("verified" in r for r, _ in rows)
            else None,
            "wrong_verified": sum(row.get("verified") is True and not row["right"] for row, _ in rows),
            **paper_errors(done),
            "median_ms": statistics.median(row["ms"] for row, _ in rows),
            "ratio_to": ratios,
        }
    return result


def run_set(methods: Methods, pairs: list[harness.Pair], rotation_start: int) -> list[dict]:
    rows = []
    for index, pair in enumerate(pairs):
        prepared = {
            "feeds": methods.network.prepare(pair.source, pair.target),
            "body": harness.npz_body(pair.source, pair.target),
        }
        # Rotated from pair to pair, and reversed every other pair: no method always runs right after another.
        names = methods.names if index % 2 == 0 else methods.names[::-1]
        shift = (rotation_start + index) % len(names)
        results = {}
        for name in names[shift:] + names[:shift]:
            results[name] = methods.run(name, pair, prepared)
        rows.append(
            {
                "pair": pair.name,
                "points": [len(pair.source), len(pair.target)],
                "extent": pair.extent,
                "voxel": pair.voxel,
                "results": results,
            }
        )
        print(
            f"{pair.name:58s} {len(pair.source):>7d}/{len(pair.target):<7d} "
            + "  ".join(
                f"{name} {row['ms']:.0f} ms {row.get('rotation_deg', float('nan')):.2f} deg"
                for name, row in results.items()
                if row
            ),
            flush=True,
        )
    return rows


def seeds(text: str) -> list[int]:
    """ "3", "0-19" or "0,3,5" -> the seeds."""
    found = []
    for part in text.split(","):
        first, dash, last = part.partition("-")
        try:
            found += list(range(int(first), int(last) + 1)) if dash else [int(first)]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: give a seed (3), a range (0-19) or a list (0,3,5)") from None
    if not found:
        raise argparse.ArgumentTypeError(f"{text!r}: the range holds no seed")
    return found


def seeded(seeds: list[int], build: Callable[..., list[harness.Pair]], *arguments, **options) -> list[harness.Pair]:
    """build(*arguments, seed=S, **options)'s pairs for every seed S, named with their seed where
    there are several."""
    return [
        dataclasses.replace(pair, name=f"{pair.name} seed {seed}") if len(seeds) > 1 else pair
        for seed in seeds
        for pair in build(*arguments, seed=seed, **options)
    ]


def scan_pairs(names: list[str], max_angle_deg: float, seed: int) -> list[harness.Pair]:
    return [harness.scan_pair(name, seed, max_angle_deg=max_angle_deg) for name in names]


def peers(args) -> int:
    sets: dict[str, list[harness.Pair]] = {}
    for spec in args.modelnet:
        sets[f"ModelNet {spec}"] = seeded(args.seed, harness.pair_set, spec, args.modelnet_pairs)
    for spec in args.scenes:
        domain, _, shared = spec.partition(":")
        label = f"{domain} scenes" + (", shared points" if shared else "")
        sets[label] = seeded(args.seed, harness.pair_set, spec, per_scan=args.scene_pairs)
    if args.scans:
        sets["real scans"] = seeded(args.seed, scan_pairs, args.scans, args.scan_angle)
    if args.truth_pairs:
        sets["real pairs with ground truth"] = harness.truth_pairs()
    settings = harness.parse_settings(args.setting)
    with contextlib.ExitStack() as stack:
        services = {"defaults": stack.enter_context(harness.Service())}
        services |= {name: stack.enter_context(harness.Service(**values)) for name, values in settings.items()}
        methods = Methods(args, services)
        warm = next(iter(sets.values()))[0]
        prepared = {
            "feeds": methods.network.prepare(warm.source, warm.target),
            "body": harness.npz_body(warm.source, warm.target),
        }
        for name in methods.names:  # first calls, imports and connections, unmeasured
            methods.run(name, warm, prepared)
        record = {
            **harness.run_header(),
            "model": services["defaults"].model(),
            "threads": args.threads,
            "requests": {name: options for name, (_, options) in methods.requests.items() if "@" not in name},
            "settings": settings,
            "scan_angle_deg": args.scan_angle,
            "seeds": args.seed,
        }
        record["right"] = {
            "rotation_deg": harness.RIGHT_ROTATION_DEG,
            "translation_share_of_extent": harness.RIGHT_TRANSLATION_SHARE,
        }
        record["sets"] = {}
        for offset, (set_name, pairs) in enumerate(sets.items()):
            rows = run_set(methods, pairs, offset)
            record["sets"][set_name] = {"summary": summary(rows, methods.names), "pairs": rows}
            for name, s in record["sets"][set_name]["summary"].items():
                ratios = "  ".join(f"{s['ratio_to'][peer]:.2f}x {peer}" for peer in s["ratio_to"])
                median = s["median_rotation_deg"] or float("nan")
                print(f"{set_name}: {name:16s} recall {s['recall']:.2f}  median {median:.3g} deg  {ratios}")
    harness.write_record(args.out, record)
    return 0


def models(args) -> int:
    """Two or more ONNX files on the same pairs (`--sets`), called in turn, the order
    rotated pair by pair: each file's time as its median per-pair ratio to the first file's, and its
    rotation error alone on each set (mean and median, degrees); with `--refine`, also after the
    service's coarse-to-fine GICP (mean, median, and the share of pairs right and verified)."""
    networks = [harness.Network(path, args.threads) for path in args.models]
    sets = {spec: harness.pair_set(spec, args.pairs, args.seed) for spec in args.sets}
    ms = []
    errors = {spec: [[] for _ in networks] for spec in sets}
    refined = {spec: [[] for _ in networks] for spec in sets}
    for spec, pairs in sets.items():
        for k, pair in enumerate(pairs):
            prepared = [network.prepare(pair.source, pair.target) for network in networks]
            clouds = AlignmentClouds(pair.source, pair.target) if args.refine else None
            row = np.zeros(len(networks))
            for i in np.roll(np.arange(len(networks)), k):
                feeds, normalisation = prepared[i]
                networks[i].call(feeds)  # warm: the first call of a new point count plans the graph
                (rotation, translation), row[i] = timed(networks[i].call, feeds)
                answer = networks[i].to_user_units(normalisation, rotation, translation)
                errors[spec][i].append(harness.errors(pair, *answer)["rotation_deg"])
                if clouds is not None:
                    refined[spec][i].append(refined_errors(pair, clouds, normalisation, answer))
            ms.append(row)
    ratios = np.median(np.array(ms) / np.array(ms)[:, :1], axis=0)
    print(f"{len(ms)} pairs; time: median per-pair ratio to the first file; rotation error, deg")
    for i, path in enumerate(args.models):
        print(f"{ratios[i]:5.2f}x  {path}")
        for spec in sets:
            line = f"    {spec:16s} alone mean {np.mean(errors[spec][i]):.3f} median {np.median(errors[spec][i]):.3f}"
            if args.refine:
                rows = np.array(refined[spec][i])
                line += (
                    f"  refined mean {rows[:, 0].mean():.3f} median {np.median(rows[:, 0]):.4f}"
                    f"  right {rows[:, 1].mean():.2f}  verified {rows[:, 2].mean():.2f}  wrong and verified "
                    f"{int((rows[:, 2] * (1 - rows[:, 1])).sum())}"
                )
            print(line)
    return 0


def refined_errors(pair: harness.Pair, clouds: AlignmentClouds, normalisation, answer) -> tuple[float, float, float]:
    """Rotation error, right, verified of an answer refined as the service refines it (coarse, then fine)."""
    rotation, translation = answer
    for distance in refine_distances(clouds.spacing, normalisation.scale):
        rotation, translation, _ = clouds.refine(rotation, translation, distance)
    found = harness.errors(pair, rotation, translation)
    return found["rotation_deg"], float(found["right"]), float(clouds.verify(rotation, translation).verified)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads of the network call alone")
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("peers", help="network, service requests and classical peers on the same pairs")
    p.add_argument("--model", type=Path, default=harness.MODEL, help="ONNX file of the network-alone row")
    p.add_argument(
        "--modelnet", nargs="*", default=["same:clean"], help="split:noise[:so3] sets of the paper's protocol"
    )
    p.add_argument("--modelnet-pairs", type=int, default=25)
    p.add_argument(
        "--scenes",
        nargs="*",
        default=[],
        choices=["indoor", "outdoor", "indoor:shared", "outdoor:shared"],
        help="the paper's scene protocol on the scans of the scenes held out of training; "
        "':shared': both clouds one sample of the scan, as the paper's own pairs",
    )
    p.add_argument("--scene-pairs", type=int, default=1, help="pairs per held-out scan")
    p.add_argument(
        "--scans", nargs="*", default=list(harness.DEFAULT_SCANS), help="archive/name of scans in the shared data"
    )
    p.add_argument("--scan-angle", type=float, default=30.0, help="largest rotation of a scan pair, degrees")
    p.add_argument("--truth-pairs", action=argparse.BooleanOptionalAction, default=True, help="the real indoor pairs")
    p.add_argument("--request", action="append", default=None, help="NAME=JSON options: one service row each")
    p.add_argument(
        "--setting",
        action="append",
        default=[],
        help="NAME=KEY=VALUE[,KEY=VALUE]: IFNET_* of one more server, asked every request too (rows REQUEST@NAME)",
    )
    p.add_argument("--tight-max-points", type=int, default=5000, help="open3d-tight only on pairs this small")
    p.add_argument(
        "--seed", type=seeds, default=[0], help="the pairs' seed, or several (0-19, 0,3,5): a set holds every seed's"
    )
    p.add_argument("--out", type=Path, default=harness.RESULTS / "compare.json")
    m = commands.add_parser("models", help="ONNX files' calls interleaved on the same pairs: time and accuracy")
    m.add_argument("models", type=Path, nargs="+")
    m.add_argument("--pairs", type=int, default=20, help="pairs per set")
    m.add_argument(
        "--sets",
        nargs="+",
        default=["same:clean", "same:jitter"],
        help="set names as bench.harness.pair_set takes them (ModelNet split:noise[:so3], indoor, outdoor:shared, ...)",
    )
    m.add_argument("--refine", action="store_true", help="also the errors after the service's refinement")
    m.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.command == "peers":
        args.request = args.request or list(DEFAULT_REQUESTS)
        for spec in args.request:
            name, _, options = spec.partition("=")
            if not name or not isinstance(json.loads(options or "null"), dict):
                parser.error(f"--request {spec!r}: give NAME=JSON-object")
        return peers(args)
    if len(args.models) < 2:
        parser.error("give at least two ONNX files")
    return models(args)


if __name__ == "__main__":
    sys.exit(main())
