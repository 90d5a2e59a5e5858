"""Scene registration pairs from real scans, by the paper's indoor and outdoor protocols.

Indoor (7Scenes, ICL-NUIM in the paper): each cloud is 2,048 points resampled from the scan, the
target moved by the motion, and each kept to the 1,536 points nearest one shared far point.
Outdoor (KITTI): the scan voxelised at 0.3 m, then 2,048 points per cloud. Unlike the paper, the
two clouds are drawn from disjoint halves of the scan, so that they share no exact point, as two
captures of one scene do. Scans are split by scene: a held-out scene never reaches training.

The network sees each pair as the service hands it over: both clouds sampled to its point count
by farthest-point sampling and normalised (`model.geometry.Normalisation`). Each pair also carries
the paper's version of itself (both clouds from one sample, so they share points), in the same
frame, for a teacher: the same (R, t) aligns both.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from model.geometry import (
    Normalisation,
    apply_transform,
    at_most,
    crop_nearest,
    disjoint_halves,
    exactly,
    random_rotation,
    voxel_downsample,
)
from model.training.data import DEFAULT_DATA_DIR

SCAN_FILES = {"indoor": "indoor_scans.npz", "outdoor": "lidar_scans.npz"}
# Held out for evaluation. Indoor: the scenes of the real pairs with ground truth (o3d-rgbd-seq,
# iclnuim-slambook2), a tabletop scene beside the trained one, and rooms from four other sources.
HELD_OUT_SCENES = {
    "indoor": (
        "o3d-rgbd-seq",
        "iclnuim-slambook2",
        "tum-fr1-slambook2",
        "osd-test",
        "scannet-scene0000_00",
        "pcl-pairwise",
        "sunrgbd-val-votenet-000004",
        "sunrgbd-val-votenet-000005",
        "sunrgbd-val-votenet-000006",
        "sunrgbd-val-votenet-000007",
    ),
    # KITTI sequence 08 is the paper's test sequence too.
    "outdoor": ("kitti-obj-testing", "semkitti-seq08"),
}


def scene_of(scan_name: str) -> str:
    """`<source>__<scene>__<id>` -> scene."""
    return scan_name.split("__")[1]


def load_scans(domain: str, part: str, data_dir: Path | str | None = None) -> dict[str, np.ndarray]:
    """Scans of a domain by name: part "train" (every scene not held out) or "test" (the held-out scenes)."""
    if domain not in SCAN_FILES:
        raise ValueError(f"unknown domain {domain!r}; choose one of {sorted(SCAN_FILES)}")
    if part not in ("train", "test"):
        raise ValueError(f"part must be 'train' or 'test', got {part!r}")
    path = Path(data_dir or DEFAULT_DATA_DIR) / SCAN_FILES[domain]
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: pass --data-dir pointing at ../shared/data (see its README.md)")
    held_out = HELD_OUT_SCENES[domain]
    with np.load(path) as archive:
        return {
            name: archive[name].astype(np.float64)
            for name in sorted(archive.files)
            if (scene_of(name) in held_out) == (part == "test")
        }


@dataclass(frozen=True)
class ScanProtocol:
    sample_points: int = 2048
    crop_points: int | None = 1536  # None: whole clouds (the outdoor protocol)
    voxel: float | None = None  # metres, before sampling
    max_angle_deg: float = 45.0
    max_translation: float = 0.5


PROTOCOLS = {"indoor": ScanProtocol(), "outdoor": ScanProtocol(crop_points=None, voxel=0.3)}


def make_scan_pair(scan: np.ndarray, protocol: ScanProtocol, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """source, target (in the scan's units) and the true (R, t) source -> target."""
    points = voxel_downsample(scan, protocol.voxel) if protocol.voxel else scan
    halves = disjoint_halves(points, rng)
    source, target = (
        half[rng.choice(len(half), size=min(protocol.sample_points, len(half)), replace=False)] for half in halves
    )
    # One sample for both clouds, the paper's way: a teacher's pair (teacher_view).
    shared = points[rng.choice(len(points), size=min(protocol.sample_points, len(points)), replace=False)]
    rotation, _ = random_rotation(rng, protocol.max_angle_deg)
    translation = rng.uniform(-protocol.max_translation, protocol.max_translation, size=3)
    target = apply_transform(target, rotation, translation)
    anchor = None
    if protocol.crop_points:
        # One far direction, shared by both clouds in their own frames, as the ModelNet protocol does.
        anchor = scan.mean(axis=0) + np.ptp(scan, axis=0).max() * 500.0 * rng.normal(size=3)
        source, target = (crop_nearest(cloud, anchor, protocol.crop_points) for cloud in (source, target))
    return {
        "source": source,
        "target": target,
        "rotation": rotation,
        "translation": translation,
        "shared": shared,
        "anchor": anchor,
    }


def teacher_view(pair: dict, points: int, protocol: ScanProtocol) -> tuple[np.ndarray, np.ndarray]:
    """The pair as the paper builds it, at the network's point count: one sample of the scan, moved,
    and both copies cropped alike, so that the clouds share their points where they overlap."""
    keep = round(points * protocol.sample_points / protocol.crop_points) if protocol.crop_points else points
    shared = at_most(pair["shared"], keep)
    source, target = shared, apply_transform(shared, pair["rotation"], pair["translation"])
    if pair["anchor"] is not None:
        source, target = (crop_nearest(cloud, pair["anchor"], points) for cloud in (source, target))
    return exactly(source, points), exactly(target, points)  # a small scan's crops fall short of `points`


def network_view(source: np.ndarray, target: np.ndarray, points: int) -> tuple[np.ndarray, np.ndarray, Normalisation]:
    """The clouds as the service gives them to the network: `points` each (farthest-point sampled, or
    filled up with repeats), normalised."""
    source, target = exactly(source, points), exactly(target, points)
    normalisation = Normalisation(source, target)
    return (
        normalisation.source(source).astype(np.float32),
        normalisation.target(target).astype(np.float32),
        normalisation,
    )


class ScanPairs(Dataset):
    """Pairs from scans, network-ready; pair i depends only on (seed, epoch, i) like RegistrationPairs."""

    def __init__(self, scans: list[np.ndarray], protocol: ScanProtocol, network_points: int, seed: int = 0):
        self.scans = scans
        self.protocol = protocol
        self.network_points = network_points
        self.seed = seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.scans)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng((self.seed, self.epoch, index))
        pair = make_scan_pair(self.scans[index], self.protocol, rng)
        source, target, normalisation = network_view(pair["source"], pair["target"], self.network_points)
        # The teacher's pair in the student's frame, so that one (R, t) aligns both pairs.
        shared_source, shared_target = teacher_view(pair, self.network_points, self.protocol)
        return {
            "source": torch.from_numpy(source),
            "target": torch.from_numpy(target),
            "rotation": torch.from_numpy(pair["rotation"].astype(np.float32)),
            "noise_free_source": torch.from_numpy(normalisation.source(shared_source).astype(np.float32)),
            "noise_free_target": torch.from_numpy(normalisation.target(shared_target).astype(np.float32)),
        }
