"""ModelNet registration pairs by the paper's protocol (as the official code builds them).

Each pair: a shape of 1,024 points, a rotation from three Euler angles uniform in [0, 45] deg, a
translation uniform in [-0.5, 0.5] per axis; the source and the moved copy are each cropped to
the 768 points nearest to one shared far point (partial-to-partial). Noise variants: "outliers"
(100 extra points copied from the cloud, offset by N(0, 0.5^2) clipped to [-1, 1]) and "jitter"
(Gaussian noise sigma 0.01 clipped to 0.05 on every point, both clouds independently). Evaluation
pairs are seeded by index.
"""

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from model.geometry import apply_transform, crop_nearest, farthest_point_sample, random_rotation

DEFAULT_DATA_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data"
SPLIT_FILES = {"train": "modelnet10_train.npz", "same": "modelnet10_test.npz", "unseen": "modelnet40_unseen.npz"}
NOISE_KINDS = ("clean", "outliers", "jitter")
OUTLIER_COUNT = 100


def load_split(split: str, data_dir: Path | str | None = None) -> np.ndarray:
    """Shapes [S, 1024, 3] of a split; a clear error where the data is missing."""
    if split not in SPLIT_FILES:
        raise ValueError(f"unknown split {split!r}; choose one of {sorted(SPLIT_FILES)}")
    path = Path(data_dir or DEFAULT_DATA_DIR) / SPLIT_FILES[split]
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: pass --data-dir pointing at a folder with {SPLIT_FILES[split]} "
            "(an .npz with a 'points' array [shapes, points, 3]), see ../shared/data/README.md"
        )
    with np.load(path) as archive:
        return archive["points"].astype(np.float32)


@dataclass(frozen=True)
class Protocol:
    num_points: int = 1024
    crop_points: int = 768
    max_angle_deg: float = 45.0
    max_translation: float = 0.5
    noise: str = "clean"
    jitter_sigma: float = 0.01  # of the "jitter" noise, clipped to 5 sigma
    # Jitter the shape once, before the motion and the crops, so that both clouds keep exact shared
    # (noisy) points: a diagnostic separating the noise itself from the loss of shared points.
    shared_jitter: bool = False

    def __post_init__(self):
        if self.noise not in NOISE_KINDS:
            raise ValueError(f"noise must be one of {NOISE_KINDS}, got {self.noise!r}")
        if self.shared_jitter and self.noise != "jitter":
            raise ValueError("shared_jitter applies to the jitter noise only")

    @property
    def cloud_points(self) -> int:
        """Points per cloud of a pair built by this protocol."""
        return self.crop_points + (OUTLIER_COUNT if self.noise == "outliers" else 0)


def add_outliers(points: np.ndarray, rng: np.random.Generator, count: int = OUTLIER_COUNT) -> np.ndarray:
    copies = points[rng.integers(0, len(points), size=count)]
    return np.concatenate([points, copies + np.clip(rng.normal(0.0, 0.5, copies.shape), -1.0, 1.0)])


def add_jitter(points: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    return points + np.clip(rng.normal(0.0, sigma, points.shape), -5 * sigma, 5 * sigma)


def make_pair(shape: np.ndarray, protocol: Protocol, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One registration pair from one shape: source, target, the true (R, t) source->target, and
    the two clouds before their own noise (a teacher's input in training; see train.py)."""
    points = shape[: protocol.num_points].astype(np.float64)
    if protocol.shared_jitter:
        points = add_jitter(points, rng, protocol.jitter_sigma)
    rotation, _ = random_rotation(rng, protocol.max_angle_deg)
    translation = rng.uniform(-protocol.max_translation, protocol.max_translation, size=3)
    source = rng.permutation(points)
    target = rng.permutation(apply_transform(points, rotation, translation))
    # One far point, shared by both clouds in their own frames, as the official protocol does.
    anchor = rng.random(3) + 500.0 * rng.choice([-1.0, 1.0])
    source = crop_nearest(source, anchor, protocol.crop_points)
    target = crop_nearest(target, anchor, protocol.crop_points)
    noise_free = {"noise_free_source": source.astype(np.float32), "noise_free_target": target.astype(np.float32)}
    if protocol.noise == "outliers":
        source, target = add_outliers(source, rng), add_outliers(target, rng)
    elif protocol.noise == "jitter" and not protocol.shared_jitter:
        sigma = protocol.jitter_sigma
        source, target = add_jitter(source, rng, sigma), add_jitter(target, rng, sigma)
    return {
        "source": source.astype(np.float32),
        "target": target.astype(np.float32),
        "rotation": rotation.astype(np.float32),
        "translation": translation.astype(np.float32),
        **noise_free,
    }


class RegistrationPairs(Dataset):
    """Pairs built on the fly; pair i depends only on (seed, epoch, i), so evaluation sets are
    identical across runs and workers, and training draws new motions each epoch (set `epoch`).

    Given several protocols, each pair draws one of them (e.g. clean and jitter pairs mixed for
    training); they must give clouds of one size so that pairs batch together. A network of fewer
    points than the clouds (`network_points`) gets each cloud farthest-point sampled down to its
    count from a random start, as the service samples; the noise-free clouds stay whole.
    """

    def __init__(
        self,
        shapes: np.ndarray,
        protocols: Protocol | Sequence[Protocol] = Protocol(),
        seed: int = 0,
        network_points: int | None = None,
    ):
        self.shapes = shapes
        self.network_points = network_points
        self.protocols = (protocols,) if isinstance(protocols, Protocol) else tuple(protocols)
        if len({p.cloud_points for p in self.protocols}) != 1:
            raise ValueError("protocols to mix must give clouds of one size (outliers add points: train on them alone)")
        self.seed = seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.shapes)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng((self.seed, self.epoch, index))
        # A single protocol draws nothing, so its pairs stay those of the seeded evaluation sets.
        protocol = self.protocols[rng.integers(len(self.protocols))] if len(self.protocols) > 1 else self.protocols[0]
        pair = make_pair(self.shapes[index], protocol, rng)
        if self.network_points and protocol.cloud_points > self.network_points:
            for key in ("source", "target"):
                cloud = pair[key]
                pair[key] = cloud[farthest_point_sample(cloud, self.network_points, int(rng.integers(len(cloud))))]
        return {key: torch.from_numpy(value) for key, value in pair.items()}


def synthetic_shape(rng: np.random.Generator, num_points: int = 1024) -> np.ndarray:
    """A smooth random closed surface [num_points, 3] inside the unit sphere, for tests and checks
    where ModelNet is absent: a sphere with random low-frequency bumps, stretched per axis."""
    directions = rng.normal(size=(num_points, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    frequencies = rng.normal(scale=2.0, size=(4, 3))
    phases = rng.uniform(0, 2 * np.pi, size=4)
    radius = 1.0 + 0.25 * np.sin(directions @ frequencies.T + phases).sum(axis=1) / 2.0
    points = directions * radius[:, None] * rng.uniform(0.5, 1.0, size=3)
    points -= points.mean(axis=0)
    return (points / np.linalg.norm(points, axis=1).max()).astype(np.float32)


def evaluation_pairs(count: int, noise: str = "clean", seed: int = 0, data_dir: Path | str | None = None) -> list[dict]:
    """`count` seeded protocol pairs from ModelNet10 test shapes, or from synthetic shapes where
    the data is absent (so checks still run on a fresh clone)."""
    try:
        shapes = load_split("same", data_dir)[:count]
    except FileNotFoundError:
        shapes = np.stack([synthetic_shape(np.random.default_rng((seed, i))) for i in range(count)])
    protocol = Protocol(noise=noise)
    return [make_pair(shape, protocol, np.random.default_rng((seed, i))) for i, shape in enumerate(shapes)]
