"""Train IFNet with the paper's unsupervised losses.

    python -m model.training.train --preset fast --epochs 2 --out runs/fast
    python -m model.training.train --domain indoor --init-weights model/weights/ifnet-fast.pt \
        --override edgeconv_k=16 --teacher model/weights/ifnet-fast.pt --lr 5e-4 --epochs 27 \
        --out runs/indoor                                                # scene pairs from real scans

Writes <out>/checkpoint.pt every --checkpoint-every steps (and at the end), a CSV log of the
losses, and losses.png. Rerunning the same command resumes from the checkpoint.
"""

import argparse
import csv
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from model.checkpoint import load_checkpoint, read_weights, shipped_record
from model.cli import (
    UserError,
    load_torch_file,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    reports_user_errors,
)
from model.geometry import apply_transform, point_spacing, refine, rotation_angle_deg
from model.ifnet import PRESETS, IFNet, IFNetConfig, preset
from model.training.data import DEFAULT_DATA_DIR, NOISE_KINDS, Protocol, RegistrationPairs, load_split
from model.training.losses import ifnet_losses, teacher_consistency_loss
from model.training.scenes import PROTOCOLS, ScanPairs, load_scans

PROG = "python -m model.training.train"

LOG_FIELDS = [
    "step",
    "epoch",
    "lr",
    "total",
    "global_registration",
    "neighbourhood_consistency",
    "pseudo_consistency",
    "teacher_consistency",
    "val_rotation_deg",
    "val_jitter_rotation_deg",
    "seconds",
]
# Log column -> noise of its held-out pairs. Validated on clean and on jittered pairs: a network
# can match clean pairs by their exact shared points and still fail once the clouds are sampled apart.
VALIDATION_COLUMNS = {"val_rotation_deg": "clean", "val_jitter_rotation_deg": "jitter"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--domain",
        default="object",
        choices=["object", *PROTOCOLS],
        help="training pairs: ModelNet10 objects (default), or real indoor or outdoor scans of the scenes "
        "not held out for evaluation (model/training/scenes.py)",
    )
    parser.add_argument("--preset", default="fast", choices=sorted(PRESETS), help="model size (default: fast)")
    parser.add_argument(
        "--override",
        nargs="+",
        default=[],
        metavar="FIELD=INT",
        help="change integer fields of the preset's config, e.g. --override edgeconv_k=16 (for experiments)",
    )
    parser.add_argument("--epochs", type=positive_float, default=2.0, help="may be fractional (default: 2)")
    parser.add_argument("--batch-size", type=positive_int, default=4, help="pairs per step (default: 4)")
    parser.add_argument("--lr", type=positive_float, default=1e-3, help="Adam learning rate (the paper's 1e-3)")
    parser.add_argument(
        "--schedule", choices=["cosine", "constant"], default="cosine", help="learning rate over the run"
    )
    parser.add_argument("--seed", type=int, default=3407, help="of the weights and the training pairs")
    parser.add_argument("--data-dir", type=Path, default=DEFAULT_DATA_DIR, help="folder holding modelnet10_train.npz")
    parser.add_argument(
        "--out", type=Path, default=Path("runs/default"), help="run folder: checkpoint, log, plot (resumed if present)"
    )
    parser.add_argument("--checkpoint-every", type=positive_int, default=100, help="steps between checkpoints")
    parser.add_argument("--val-shapes", type=positive_int, default=64, help="training shapes held out for validation")
    parser.add_argument(
        "--max-shapes", type=non_negative_int, default=0, help="train on the first N shapes only (0: all)"
    )
    parser.add_argument(
        "--max-steps", type=non_negative_int, default=0, help="stop after this many steps (0: no limit)"
    )
    parser.add_argument("--threads", type=non_negative_int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument(
        "--device",
        default="cuda" if torch.cuda.is_available() else "cpu",
        help="torch device (default: cuda when a GPU is visible, else cpu)",
    )
    parser.add_argument(
        "--noise",
        nargs="+",
        choices=NOISE_KINDS,
        default=["clean"],
        help="noise of the training pairs; several kinds are mixed pair by pair (e.g. --noise clean jitter)",
    )
    parser.add_argument(
        "--jitter-sigma",
        type=non_negative_float,
        default=Protocol.jitter_sigma,
        help="sigma of the training pairs' jitter (validation keeps the evaluation's 0.01); "
        "raising it over successive fine-tunes makes a noise curriculum",
    )
    parser.add_argument(
        "--global-weight",
        type=float,
        default=1.0,
        help="weight of the global registration loss (the paper's 1; the other two keep 1), for experiments",
    )
    parser.add_argument(
        "--global-loss",
        choices=["squared", "distance"],
        default="squared",
        help="Huber of squared nearest-neighbour distances (the paper's) or of the distances, for experiments",
    )
    parser.add_argument(
        "--teacher",
        type=Path,
        help="weights of a trained network whose (R, t) on each pair before its noise every block is pulled "
        "towards (--teacher-weight): a registration signal on noisy pairs without the true pose",
    )
    parser.add_argument(
        "--teacher-weight",
        type=non_negative_float,
        default=1000.0,
        help="weight of the teacher consistency loss (its gradient is ~1/100 of the neighbourhood loss's)",
    )
    parser.add_argument(
        "--teacher-blocks",
        choices=["every", "last"],
        default="every",
        help="blocks the teacher pulls: every block, or each time step's last (its finished estimate), for experiments",
    )
    parser.add_argument("--init-weights", type=Path, help="start from these weights (fine-tuning) instead of random")
    return parser.parse_args(argv)


def parse_overrides(items: list[str]) -> dict[str, int]:
    integer_fields = [f.name for f in dataclasses.fields(IFNetConfig) if f.type is int]
    overrides = {}
    for item in items:
        field, _, value = item.partition("=")
        if field not in integer_fields or not value.lstrip("-").isdigit():
            raise UserError(f"--override {item!r}: expected FIELD=INT with FIELD one of {integer_fields}")
        overrides[field] = int(value)
    return overrides


def learning_rate(args: argparse.Namespace, step: int, total_steps: int) -> float:
    if args.schedule == "constant":
        return args.lr
    return args.lr * 0.5 * (1.0 + math.cos(math.pi * min(step / max(total_steps, 1), 1.0)))


def training_pairs(shapes: np.ndarray, args: argparse.Namespace, network_points: int) -> RegistrationPairs:
    """The training pairs: --noise kinds mixed pair by pair, jitter of --jitter-sigma."""
    protocols = [Protocol(noise=kind, jitter_sigma=args.jitter_sigma) for kind in args.noise]
    return RegistrationPairs(shapes, protocols, seed=args.seed, network_points=network_points)


def object_pairs(
    args: argparse.Namespace, config: IFNetConfig
) -> tuple[RegistrationPairs, dict[str, RegistrationPairs]]:
    """ModelNet10 training pairs and the held-out validation pairs of each VALIDATION_COLUMNS noise."""
    shapes = load_split("train", args.data_dir)
    if args.val_shapes >= len(shapes):
        raise UserError(f"--val-shapes {args.val_shapes} leaves nothing to train on: the split has {len(shapes)}")
    val_shapes, train_shapes = shapes[-args.val_shapes :], shapes[: -args.val_shapes]
    if args.max_shapes:
        train_shapes = train_shapes[: args.max_shapes]
    try:
        train_pairs = training_pairs(train_shapes, args, config.num_points)
    except ValueError as error:  # kinds of noise that cannot be mixed
        raise UserError(f"--noise {' '.join(args.noise)}: {error}") from None
    validation = {
        column: RegistrationPairs(
            val_shapes, Protocol(noise=noise), seed=args.seed + 1, network_points=config.num_points
        )
        for column, noise in VALIDATION_COLUMNS.items()
    }
    return train_pairs, validation


# Validation pairs per held-out scan: the outdoor domain holds out only 12 scans.
VALIDATION_PAIRS_PER_SCAN = {"indoor": 1, "outdoor": 4}


def scene_pairs(args: argparse.Namespace, config: IFNetConfig) -> tuple[ScanPairs, dict[str, ScanPairs]]:
    """Pairs from the domain's training scenes; validation on its held-out scenes (two captures of
    one scene share no point, so these pairs are all of the "jitter" kind: one column)."""
    if args.noise != ["clean"]:
        raise UserError(f"--domain {args.domain}: --noise applies to object pairs only (scene pairs are two captures)")
    try:
        train_scans, test_scans = (
            list(load_scans(args.domain, part, args.data_dir).values()) for part in ("train", "test")
        )
    except FileNotFoundError as error:
        raise UserError(str(error)) from None
    if args.max_shapes:
        train_scans = train_scans[: args.max_shapes]
    protocol = PROTOCOLS[args.domain]
    validation = test_scans * VALIDATION_PAIRS_PER_SCAN[args.domain]
    return ScanPairs(train_scans, protocol, config.num_points, seed=args.seed), {
        "val_rotation_deg": ScanPairs(validation, protocol, config.num_points, seed=args.seed + 1)
    }


def load_teacher(path: Path, device: str) -> IFNet:
    teacher = load_checkpoint(path).model
    return teacher.to(device).requires_grad_(False)


def load_weights_into(model: IFNet, path: Path, option: str) -> None:
    state = read_weights(path, option)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError:  # parameter shapes differ
        raise UserError(
            f"{option} {path}: weights of another model size; pass their --preset (and --override)"
        ) from None


def check_device(device: str) -> None:
    try:
        kind = torch.device(device).type
    except RuntimeError:
        raise UserError(f"--device {device}: not a torch device; use cpu or cuda") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {device}: torch sees no CUDA GPU here; use --device cpu")


@torch.no_grad()
def taught_transform(
    teacher: IFNet, batch: dict[str, torch.Tensor], device: str, polish: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The teacher's (R, t) on the pair before noise (or its shared-point version), and which pairs
    it answered [B]. `polish` (scene pairs): its estimate refined by GICP, and kept only where the
    clouds' shared points then coincide; a few degrees off is a poor teacher, a polished one exact."""
    source, target = batch["noise_free_source"], batch["noise_free_target"]
    out = teacher(source.to(device), target.to(device))
    rotation, translation = out.rotation.cpu().double().numpy(), out.translation.cpu().double().numpy()
    taught = np.ones(len(rotation))
    if polish:
        for i, (src, tgt) in enumerate(zip(source.double().numpy(), target.double().numpy(), strict=True)):
            rotation[i], translation[i], _ = refine(src, tgt, rotation[i], translation[i])
            taught[i] = shared_points_coincide(apply_transform(src, rotation[i], translation[i]), tgt)
    return (torch.from_numpy(array).float().to(device) for array in (rotation, translation, taught))


# A polished teacher's pose (GICP stops up to ~0.15 deg off) puts most points both clouds share within
# a tenth of a point spacing of each other; a wrong one, degrees off, leaves few there.
COINCIDENT_SPACINGS, MIN_COINCIDENT_SHARE = 0.1, 0.2


def coincident_share(moved: np.ndarray, target: np.ndarray, spacings: float = COINCIDENT_SPACINGS) -> float:
    """Share of the moved points within `spacings` of the target's point spacing of a target point."""
    distances, _ = cKDTree(target).query(moved)
    return float(np.mean(distances < spacings * point_spacing(target)))


def shared_points_coincide(moved: np.ndarray, target: np.ndarray) -> bool:
    return coincident_share(moved, target) >= MIN_COINCIDENT_SHARE


@torch.no_grad()
def validate(model: IFNet, pairs: RegistrationPairs, device: str, batch_size: int) -> float:
    """Mean isotropic rotation error (deg) on held-out pairs; monitoring only, not a loss."""
    was_training = model.training
    model.eval()
    errors = []
    for batch in DataLoader(pairs, batch_size=batch_size):
        out = model(batch["source"].to(device), batch["target"].to(device))
        errors.append(rotation_angle_deg(out.rotation.cpu().double().numpy(), batch["rotation"].double().numpy()))
    model.train(was_training)
    return float(np.concatenate(errors).mean())


def save_checkpoint(
    path: Path, model: IFNet, optimizer: torch.optim.Optimizer, step: int, args: argparse.Namespace, origin: dict
):
    """`origin`: {"fine_tuned_from": record} of the weights the run started from, read at its start
    (ship keeps it in the shipped record); empty for a run resumed from a checkpoint without it."""
    state = origin | {
        "model": model.state_dict(),
        "config": model.config.to_dict(),
        "preset": args.preset,
        "optimizer": optimizer.state_dict(),
        "step": step,
        "args": recorded_args(args),
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)  # atomic: a kill mid-write never leaves a broken checkpoint


def recorded_args(args: argparse.Namespace) -> dict:
    return {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}


def changed_options(saved: dict, args: argparse.Namespace) -> list[str]:
    """This run's options that differ from those its checkpoint was written with (--out aside):
    legitimate (e.g. more --epochs to train on), but they change the run, e.g. its lr schedule."""
    current = recorded_args(args)
    return [
        f"--{name.replace('_', '-')} {current[name]} (checkpoint: {saved[name]})"
        for name in sorted(current.keys() & saved.keys())
        if name != "out" and current[name] != saved[name]
    ]


def truncate_log(log_path: Path, step: int) -> float:
    """Drop log rows written after the checkpoint a run resumes from (they will be redone);
    returns the training seconds logged up to it, so that the clock continues across resumes."""
    with log_path.open() as f:
        rows = [row for row in csv.DictReader(f) if int(row["step"]) <= step]
    with log_path.open("w", newline="") as f:
        writer = csv.DictWriter(f, LOG_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    return float(rows[-1]["seconds"]) if rows else 0.0


def plot_losses(log_path: Path, png_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with log_path.open() as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    steps = [int(r["step"]) for r in rows]
    fig, axes = plt.subplots(1, 5, figsize=(20, 3.5))
    for ax, key in zip(axes, LOG_FIELDS[3:7]):
        ax.plot(steps, [float(r[key]) for r in rows], lw=0.6)
        ax.set_title(key)
        ax.set_xlabel("step")
        ax.set_yscale("log")
    for column, noise in VALIDATION_COLUMNS.items():
        val = [(s, float(r[column])) for s, r in zip(steps, rows) if r.get(column)]
        if val:
            axes[4].plot(*zip(*val), marker="o", label=noise)
    axes[4].set_yscale("log")
    axes[4].legend()
    axes[4].set_title("validation rotation error (deg)")
    axes[4].set_xlabel("step")
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)


def train(args: argparse.Namespace) -> Path:
    try:
        config: IFNetConfig = preset(args.preset, **parse_overrides(args.override))
    except ValueError as error:
        raise UserError(f"--override: {error}") from None
    check_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    checkpoint_path, log_path = args.out / "checkpoint.pt", args.out / "log.csv"
    resumed = None
    if checkpoint_path.exists():
        resumed = load_torch_file(checkpoint_path, "checkpoint to resume", weights_only=False)
    if resumed is not None and IFNetConfig.from_dict(resumed["config"]) != config:
        raise UserError(f"{checkpoint_path} holds a different preset or overrides; use another --out")

    train_pairs, validation = (object_pairs if args.domain == "object" else scene_pairs)(args, config)
    if args.batch_size > len(train_pairs):
        raise UserError(f"--batch-size {args.batch_size} is more than the {len(train_pairs)} training shapes")

    model = IFNet(config).to(args.device)
    teacher = load_teacher(args.teacher, args.device) if args.teacher else None
    n = config.n_iters
    teacher_blocks = slice(n - 1, None, n) if args.teacher_blocks == "last" else slice(None)
    optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)
    step, seconds_before = 0, 0.0
    if resumed is not None:
        origin = {"fine_tuned_from": resumed["fine_tuned_from"]} if "fine_tuned_from" in resumed else {}
        model.load_state_dict(resumed["model"])
        optimizer.load_state_dict(resumed["optimizer"])
        step = resumed["step"]
        seconds_before = truncate_log(log_path, step)
        print(f"resumed from {checkpoint_path} at step {step}")
        if changed := changed_options(resumed.get("args", {}), args):
            print("options differ from the checkpoint's; training continues with the new ones: " + ", ".join(changed))
    else:
        # Read now: shipping this run over its starting weights would replace their record.
        origin = {"fine_tuned_from": shipped_record(args.init_weights)}
        if args.init_weights:
            load_weights_into(model, args.init_weights, "--init-weights")
        log_path.write_text(",".join(LOG_FIELDS) + "\n")

    steps_per_epoch = len(train_pairs) // args.batch_size
    total_steps = int(args.epochs * steps_per_epoch)
    if args.max_steps:
        total_steps = min(total_steps, args.max_steps)
    print(
        f"preset {args.preset}: {model.num_parameters():,} parameters, {len(train_pairs)} training shapes, "
        f"{steps_per_epoch} steps/epoch, {total_steps} steps"
    )

    model.train()
    progress = tqdm(total=total_steps, initial=step, dynamic_ncols=True)
    running: dict[str, float] = {}
    started = time.time() - seconds_before
    with log_path.open("a", newline="") as log_file:
        log = csv.DictWriter(log_file, LOG_FIELDS)
        while step < total_steps:
            # Each epoch's order depends only on (seed, epoch), so a resumed run skips exactly
            # the batches it already trained on.
            epoch, offset = divmod(step, steps_per_epoch)
            train_pairs.epoch = epoch
            order = np.random.default_rng((args.seed, epoch)).permutation(len(train_pairs))
            order = order[offset * args.batch_size : steps_per_epoch * args.batch_size]
            for batch in DataLoader(Subset(train_pairs, order.tolist()), batch_size=args.batch_size):
                for group in optimizer.param_groups:
                    group["lr"] = learning_rate(args, step, total_steps)
                target = batch["target"].to(args.device)
                output = model(batch["source"].to(args.device), target)
                losses = ifnet_losses(output, target, config, global_on_distances=args.global_loss == "distance")
                objective = losses.weighted(args.global_weight)
                taught = torch.zeros(())
                if teacher is not None:
                    rotation, translation, answered = taught_transform(
                        teacher, batch, args.device, polish=args.domain != "object"
                    )
                    taught = teacher_consistency_loss(output, rotation, translation, teacher_blocks, answered)
                    objective = objective + args.teacher_weight * taught
                optimizer.zero_grad(set_to_none=True)
                objective.backward()
                optimizer.step()
                step += 1

                values = {
                    "total": losses.total.item(),
                    **{k: v.item() for k, v in losses._asdict().items()},
                    "teacher_consistency": taught.item(),
                }
                running = {k: 0.9 * running.get(k, v) + 0.1 * v for k, v in values.items()}
                progress.set_postfix({k[:6]: f"{v:.3g}" for k, v in running.items()})
                progress.update()
                row = {
                    "step": step,
                    "epoch": f"{step / steps_per_epoch:.3f}",
                    "lr": f"{optimizer.param_groups[0]['lr']:.3g}",
                    "seconds": f"{time.time() - started:.1f}",
                    **dict.fromkeys(validation, ""),
                    **values,
                }
                if step % args.checkpoint_every == 0 or step == total_steps:
                    for column, pairs in validation.items():
                        row[column] = f"{validate(model, pairs, args.device, args.batch_size):.4f}"
                    errors = ", ".join(f"{row[column]} deg ({column})" for column in validation)
                    progress.write(f"step {step}: validation rotation error {errors}")
                    save_checkpoint(checkpoint_path, model, optimizer, step, args, origin)
                log.writerow(row)
                log_file.flush()
                if row["val_rotation_deg"]:
                    plot_losses(log_path, args.out / "losses.png")
                if step >= total_steps:
                    break
    progress.close()
    (args.out / "summary.json").write_text(json.dumps({"steps": step, "epochs": step / steps_per_epoch}, indent=2))
    return checkpoint_path


@reports_user_errors(PROG)
def main(argv: list[str] | None = None) -> None:
    train(parse_args(argv))


if __name__ == "__main__":
    main()
