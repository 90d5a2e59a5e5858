"""Variants of `auto`'s pipeline (or `global`'s, with --method) on the same pairs in one process,
interleaved pair by pair: the A/B behind a change to one of the pipeline's constants or settings,
before and after.

    python -m bench.ab --sets indoor truth same:jitter:so3:100 \
        --variant 'look=service.registration.SLIDE_GUESS_SHARE=-1' --variant spare=
    python -m bench.ab --sets scans truth --variant 'wide=settings.fps_max_input_points=32768' --variant now=

A variant is NAME= (the code as it is) or NAME=TARGET=VALUE[;TARGET=VALUE...], where TARGET is a
module's constant (`service.registration.SLIDE_GUESS_SHARE`) or `settings.FIELD`, and VALUE is
JSON; `settings.model_repository` runs the variant on another repository's models and drafts.
Sets as bench.harness.pair_set names them: ModelNet `split:noise[:so3][:count]` (25 pairs unless
counted), `indoor`, `outdoor` (`:shared` for the paper's pairs), `truth` (the real pairs with
ground truth), `scans` (views of real scans; `scans:N`, of every scan over N points). Every
model of the repository and its draft answers in process, as the service's `auto` asks them,
with `refine`; the variants take turns first from pair to pair. Per set: right, verified and
wrong-and-verified counts, median and total time, the median of the per-pair time ratios to the
first variant, and every pair whose verdict, rightness or answer differs from the first variant's.
"""

import argparse
import asyncio
import contextlib
import importlib
import json
import statistics
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bench import harness
from model.artifacts import network_points
from service.batcher import Prediction
from service.engine import draft_file, model_files, open_session
from service.registration import Network, register_clouds
from service.schemas import RefineOptions, RegistrationOptions
from service.settings import Settings

ANSWER_TOLERANCE = 1e-6  # rotation entries further apart than this: a different answer


def parse_variant(spec: str) -> tuple[str, list[tuple[str, object]]]:
    """NAME=TARGET=VALUE;... -> (NAME, [(TARGET, value)])."""
    name, _, changes = spec.partition("=")
    if not name:
        raise SystemExit(f"--variant {spec!r}: give it a name, NAME= or NAME=TARGET=VALUE")
    patches = []
    for change in filter(None, changes.split(";")):
        target, equals, value = change.partition("=")
        if not equals or "." not in target:
            raise SystemExit(f"--variant {spec!r}: each change is module.CONSTANT=VALUE or settings.FIELD=VALUE")
        patches.append((target, json.loads(value)))
    return name, patches


@contextlib.contextmanager
def patched(patches: list[tuple[str, object]], settings: Settings) -> Iterator[Settings]:
    """The settings with the variant's fields, its constants set meanwhile (restored after)."""
    fields = {target.split(".", 1)[1]: value for target, value in patches if target.startswith("settings.")}
    undo = []
    for target, value in patches:
        if target.startswith("settings."):
            if target.split(".", 1)[1] not in Settings.model_fields:
                raise SystemExit(f"{target}: Settings has no such field")
            continue
        module_name, constant = target.rsplit(".", 1)
        module = importlib.import_module(module_name)
        if not hasattr(module, constant):
            raise SystemExit(f"{target}: {module_name} has no {constant}")
        undo.append((module, constant, getattr(module, constant)))
        setattr(module, constant, value)
    try:
        yield Settings.model_validate(settings.model_dump() | fields)  # validated: a path field becomes a Path
    finally:
        for module, constant, value in reversed(undo):
            setattr(module, constant, value)


def networks(settings: Settings) -> list[Network]:
    """The repository's models, each with its draft, in the order `auto` asks them."""

    def network(path: Path, name: str, stage: str, draft: Network | None = None) -> Network:
        session = open_session(path, settings.threads)

        async def predict(source: np.ndarray, target: np.ndarray) -> Prediction:
            started = time.perf_counter()
            rotation, translation = session.run(
                ["rotation", "translation"], {"source": source[None], "target": target[None]}
            )
            return Prediction(rotation[0], translation[0], 0.0, (time.perf_counter() - started) * 1000.0, 1)

        return Network(name, network_points(session), predict, stage, draft)

    found = []
    for path in model_files(settings):
        draft = network(draft_file(path), path.stem, "draft") if draft_file(path).is_file() else None
        found.append(network(path, path.stem, "ifnet", draft))
    return found


async def in_turn(function, *args, **kwargs):
    """register_clouds' `run_blocking` for one request at a time: each step in the calling thread."""
    return function(*args, **kwargs)


def run(args: argparse.Namespace) -> dict:
    variants = [parse_variant(spec) for spec in args.variant]
    base = Settings()
    loaded: dict[tuple, list[Network]] = {}  # per model files: a variant may serve another repository
    options = RegistrationOptions(method=args.method, refine=RefineOptions())

    def answer(pair: harness.Pair, patches: list) -> dict:
        with patched(patches, base) as settings:
            files = tuple(model_files(settings))
            if files not in loaded:
                loaded[files] = networks(settings)
            nets = loaded[files]
            started = time.perf_counter()
            result = asyncio.run(
                register_clouds(pair.source, pair.target, options, settings, nets, in_turn, base.threads)
            )
            ms = (time.perf_counter() - started) * 1000.0
        found = harness.errors(pair, result.rotation, result.translation)
        return {
            "ms": ms,
            "right": bool(found["right"]),
            "verified": bool(result.verified),
            "rotation_deg": float(found["rotation_deg"]),
            "stage": result.stage,
            "reason": result.reason,
            "rotation": np.asarray(result.rotation).tolist(),
        }

    record = harness.run_header() | {"variants": args.variant, "method": args.method, "seed": args.seed, "sets": {}}
    first = variants[0][0]
    for spec in args.sets:
        pairs = harness.pair_set(spec, seed=args.seed)
        answer(pairs[0], [])  # sessions and caches warm before anything is timed
        rows = []
        for index, pair in enumerate(pairs):
            turn = index % len(variants)
            order = variants[turn:] + variants[:turn]
            rows.append({"pair": pair.name} | {name: answer(pair, patches) for name, patches in order})
        summary = {}
        for name, _ in variants:
            times = [row[name]["ms"] for row in rows]
            summary[name] = {
                "right": sum(row[name]["right"] for row in rows),
                "verified": sum(row[name]["verified"] for row in rows),
                "wrong_verified": sum(row[name]["verified"] and not row[name]["right"] for row in rows),
                "median_ms": statistics.median(times),
                "total_ms": sum(times),
                "ratio_to_first": statistics.median(row[name]["ms"] / row[first]["ms"] for row in rows),
            }
        differing = [row for row in rows if any(differs(row[first], row[name]) for name, _ in variants[1:])]
        record["sets"][spec] = {"pairs": len(rows), "summary": summary, "differing": differing}
        print(f"{spec}: {len(rows)} pairs")
        for name, numbers in summary.items():
            print(
                f"  {name:12s} right {numbers['right']}  verified {numbers['verified']}  "
                f"wrong and verified {numbers['wrong_verified']}  median {numbers['median_ms']:.1f} ms  "
                f"total {numbers['total_ms'] / 1000:.1f} s  / {first} {numbers['ratio_to_first']:.3f}"
            )
        for row in differing:
            said = ", ".join(
                f"{name}: {row[name]['rotation_deg']:.3f} deg, verified {row[name]['verified']}" for name, _ in variants
            )
            print(f"    differs: {row['pair']} ({said})")
    return record


def differs(one: dict, other: dict) -> bool:
    """Another verdict, rightness or answer."""
    if (one["verified"], one["right"]) != (other["verified"], other["right"]):
        return True
    return bool(np.abs(np.subtract(one["rotation"], other["rotation"])).max() > ANSWER_TOLERANCE)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--sets", nargs="+", required=True, help="split:noise[:so3][:count], indoor, outdoor[:shared], truth, scans"
    )
    p.add_argument(
        "--variant", action="append", required=True, help="NAME= or NAME=TARGET=VALUE[;...]; the first is the base"
    )
    p.add_argument("--seed", type=int, default=0, help="the sets' seed: other seeds give other pairs")
    p.add_argument("--method", choices=["auto", "global"], default="auto", help="the requests' method")
    p.add_argument("--out", type=Path, help="write the record (every pair's answers) here as JSON")
    args = p.parse_args(argv)
    if len(args.variant) < 2:
        p.error("give at least two --variant")
    record = run(args)
    if args.out:
        harness.write_record(args.out, record)


if __name__ == "__main__":
    main()
