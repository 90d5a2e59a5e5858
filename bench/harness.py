"""What every benchmark shares: loopback service processes, ONNX Runtime sessions, pair sets with
known motions, the classical peers, error metrics and result files.

The service is only ever spoken to over HTTP; the network call alone is ONNX Runtime on the model
file with inputs prepared as the service prepares them (distinct points, farthest-point sampling of
a seeded subset, `model.geometry.Normalisation`).
"""

import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import httpx
import numpy as np
from scipy.spatial import cKDTree

from model.artifacts import network_points
from model.geometry import (
    Normalisation,
    exactly,
    extent,
    from_matrix,
    nearest_rotation,
    registration_errors,
    remove_duplicates,
    resample_indices,
    to_matrix,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "docs" / "benchmarks"
MODEL = ROOT / "service" / "models" / "object.onnx"
RIGHT_ROTATION_DEG = 2.0
RIGHT_TRANSLATION_SHARE = 0.02  # of the cloud's extent (bounding-box diagonal)
VOXEL_OBJECTS_INDOOR = 0.05  # metres, and unit-sphere objects
VOXEL_OUTDOOR = 0.5


# ---------------------------------------------------------------- service processes


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Service:
    """`python -m service` on a free loopback port, with this tree's packages and extra IFNET_* settings."""

    def __init__(self, log: Path | None = None, **settings):
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so that `with Service()` stops the child
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "PYTHONPATH": str(ROOT), "IFNET_LOG_LEVEL": "info" if log else "warning"}
        env.update({f"IFNET_{key.upper()}": str(value) for key, value in settings.items()})
        output = log.open("w") if log else None
        command = [sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", str(self.port)]
        self.process = subprocess.Popen(command, env=env, stdout=output, stderr=subprocess.STDOUT if log else None)
        self.pid = self.process.pid

    def wait_ready(self, timeout_s: float = 180.0) -> "Service":
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"service exited with {self.process.returncode}")
            try:
                if httpx.get(f"{self.url}/ready", timeout=2, trust_env=False).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"{self.url}/ready not 200 within {timeout_s:.0f} s")

    def stop(self) -> int:
        """SIGTERM, then SIGKILL after two minutes: never left running."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=120)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=30)
        return self.process.returncode

    def __enter__(self) -> "Service":
        return self.wait_ready()

    def __exit__(self, *exc_info) -> None:
        self.stop()

    def model(self) -> dict:
        metadata = httpx.get(f"{self.url}/v2/models/object", timeout=30, trust_env=False).json()
        return {"version": metadata["versions"][0], **metadata.get("parameters", {})}


def parse_settings(entries: list[str]) -> dict[str, dict[str, str]]:
    """`--setting NAME=KEY=VALUE[,KEY=VALUE]` entries -> {NAME: {KEY: VALUE}}: IFNET_* of one more server each."""
    return {
        name: dict(item.split("=", 1) for item in spec.split(",") if item)
        for name, _, spec in (entry.partition("=") for entry in entries)
    }


def npz_body(source: np.ndarray, target: np.ndarray) -> bytes:
    stream = io.BytesIO()
    np.savez(stream, source=source.astype(np.float32), target=target.astype(np.float32))
    return stream.getvalue()


# ---------------------------------------------------------------- the network alone


class Network:
    """One ONNX file, its point count from the file's metadata, and the service's input preparation."""

    def __init__(self, path: Path = MODEL, threads: int = 2):
        from service.engine import open_session
        from service.settings import Settings

        self.session = open_session(path, threads)
        self.points = network_points(self.session)
        self.fps_cap = Settings().fps_max_input_points

    def _sample(self, points: np.ndarray) -> np.ndarray:
        if len(points) <= self.fps_cap:
            return exactly(points, self.points)
        rng = np.random.default_rng(0)  # the service's default seed, a fresh generator per cloud
        subset = np.sort(rng.choice(len(points), size=self.fps_cap, replace=False))
        return points[subset[resample_indices(self.fps_cap, self.points, "fps", rng, points[subset])]]

    def prepare(self, source: np.ndarray, target: np.ndarray) -> tuple[dict, Normalisation]:
        source = self._sample(remove_duplicates(source.astype(np.float64)))
        target = self._sample(remove_duplicates(target.astype(np.float64)))
        normalisation = Normalisation(source, target)
        feeds = {
            "source": normalisation.source(source)[None].astype(np.float32),
            "target": normalisation.target(target)[None].astype(np.float32),
        }
        return feeds, normalisation

    def call(self, feeds: dict) -> tuple[np.ndarray, np.ndarray]:
        rotation, translation = self.session.run(["rotation", "translation"], feeds)
        return rotation[0].astype(np.float64), translation[0].astype(np.float64)

    def to_user_units(self, normalisation: Normalisation, rotation, translation) -> tuple[np.ndarray, np.ndarray]:
        return normalisation.to_user_units(nearest_rotation(rotation), translation)

    def answer(self, pair: "Pair") -> tuple[np.ndarray, np.ndarray, Normalisation]:
        """(R, t) in user units as the service computes the network's answer, and its normalisation."""
        feeds, normalisation = self.prepare(pair.source, pair.target)
        return (*self.to_user_units(normalisation, *self.call(feeds)), normalisation)


# ---------------------------------------------------------------- pairs with known motions


@dataclass
class Pair:
    name: str
    source: np.ndarray  # [N, 3] float64
    target: np.ndarray  # target ~ source @ rotation.T + translation
    rotation: np.ndarray
    translation: np.ndarray
    voxel: float  # the peers' voxel size for this kind of data

    def __post_init__(self):
        # Every method gets the float32 coordinates that the NPZ request body carries.
        self.source = self.source.astype(np.float32).astype(np.float64)
        self.target = self.target.astype(np.float32).astype(np.float64)

    @property
    def extent(self) -> float:
        return extent(self.source)  # model.geometry.extent


def uniform_rotation(rng: np.random.Generator) -> np.ndarray:
    quaternion = rng.normal(size=4)
    w, x, y, z = quaternion / np.linalg.norm(quaternion)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def modelnet_pairs(count: int, split: str = "same", noise: str = "clean", so3: bool = False, seed: int = 0):
    """The paper's protocol pairs (model.training.data), `count` shapes spread evenly over the split,
    pair i seeded by its shape's index as the evaluation seeds it; `so3` adds a uniform rotation."""
    from model.training.data import Protocol, load_split, make_pair

    shapes = load_split(split)
    pairs = []
    for index in np.linspace(0, len(shapes) - 1, min(count, len(shapes))).round().astype(int):
        rng = np.random.default_rng((seed, int(index)))
        pair = make_pair(shapes[index], Protocol(noise=noise), rng)
        rotation, translation = pair["rotation"].astype(np.float64), pair["translation"].astype(np.float64)
        target = pair["target"].astype(np.float64)
        if so3:  # a Haar-uniform rotation composed with any rotation is again uniform
            extra = uniform_rotation(np.random.default_rng((seed, int(index), 3)))
            target, rotation, translation = target @ extra.T, extra @ rotation, extra @ translation
        name = f"{split}-{noise}{'-so3' if so3 else ''}/{index}"
        pairs.append(Pair(name, pair["source"].astype(np.float64), target, rotation, translation, VOXEL_OBJECTS_INDOOR))
    return pairs


def scan_voxel(archive: str, name: str) -> float:
    outdoor = archive == "lidar_scans" or any(word in name for word in ("kitti", "nuscenes", "lidar"))
    return VOXEL_OUTDOOR if outdoor else VOXEL_OBJECTS_INDOOR


def resample_on_surface(points: np.ndarray, rng: np.random.Generator, neighbours: int = 8) -> np.ndarray:
    """Each point moved a random fraction of the way to one of its nearest neighbours: the same surface
    sampled anew, so that two views of one scan share no exact point and keep their point counts."""
    _, index = cKDTree(points).query(points, k=neighbours + 1)
    chosen = index[np.arange(len(points)), rng.integers(1, neighbours + 1, size=len(points))]
    return points + rng.uniform(0.0, 1.0, size=(len(points), 1)) * (points[chosen] - points)


def scan_pair(spec: str, seed: int = 0, keep: float = 0.7, max_angle_deg: float = 30.0) -> Pair:
    """Two overlapping views of one scan (`archive/name` in the shared data): the points below and
    above two quantiles along a random direction, each resampled on its own, the target moved by a
    rotation of up to `max_angle_deg` about a random axis and a shift of up to 10 % of the extent."""
    archive, name = spec.split("/", 1)
    with np.load(DATA / f"{archive}.npz") as data:
        points = remove_duplicates(data[name].astype(np.float64))
    rng = np.random.default_rng((seed, len(points)))
    direction = rng.normal(size=3)
    along = points @ (direction / np.linalg.norm(direction))
    low, high = np.quantile(along, [keep, 1.0 - keep])
    source = resample_on_surface(points[along <= low], rng)
    view = resample_on_surface(points[along >= high], rng)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(rng.uniform(0.0, max_angle_deg))
    rotation = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
    shift = rng.normal(size=3)
    translation = shift / np.linalg.norm(shift) * rng.uniform(0.0, 0.1 * extent(points))
    return Pair(spec, source, view @ rotation.T + translation, rotation, translation, scan_voxel(archive, name))


def scene_pairs(domain: str, per_scan: int = 1, seed: int = 0, shared: bool = False, part: str = "test") -> list[Pair]:
    """The paper's indoor or outdoor protocol (model.training.scenes) on every scan of the scenes held
    out of training (`part` "train": of the training scenes), `per_scan` pairs each, pair k of scan i
    seeded by (seed, i, k). The clouds are two disjoint samples of the scan, or with `shared` one
    sample moved, as the paper builds its pairs: then they share every point of their overlap."""
    from model.training.scenes import PROTOCOLS, load_scans, make_scan_pair, teacher_view

    protocol = PROTOCOLS[domain]
    voxel = VOXEL_OUTDOOR if domain == "outdoor" else VOXEL_OBJECTS_INDOOR
    pairs = []
    for i, (name, scan) in enumerate(load_scans(domain, part, DATA).items()):
        for k in range(per_scan):
            pair = make_scan_pair(scan, protocol, np.random.default_rng((seed, i, k)))
            source, target = pair["source"], pair["target"]
            if shared:
                source, target = teacher_view(pair, protocol.crop_points or protocol.sample_points, protocol)
            pairs.append(Pair(f"{domain}/{name}/{k}", source, target, pair["rotation"], pair["translation"], voxel))
    return pairs


def truth_pairs() -> list[Pair]:
    """The real pairs with ground truth in the shared data (indoor_pairs.npz: NAME/source, NAME/target, NAME/T)."""
    pairs = []
    with np.load(DATA / "indoor_pairs.npz") as data:
        for name in sorted({key.split("/")[0] for key in data.files}):
            transform = data[f"{name}/T"].astype(np.float64)
            source, target = (data[f"{name}/{part}"].astype(np.float64) for part in ("source", "target"))
            pairs.append(
                Pair(f"indoor_pairs/{name}", source, target, transform[:3, :3], transform[:3, 3], VOXEL_OBJECTS_INDOOR)
            )
    return pairs


# Real scans of the shared data whose two overlapping views (scan_pair) make the benchmarks' `scans` set.
SCAN_ARCHIVES = ("real_scans", "lidar_scans", "indoor_scans")
DEFAULT_SCANS = (
    "real_scans/pcl_office1",
    "real_scans/pcl_table_scene_mug",
    "real_scans/sunrgbd_000017",
    "real_scans/nuscenes_lidar_top",
    "lidar_scans/semantickitti__semkitti-seq08__000750",
    "indoor_scans/pcl__pcl-room__room_scan1",
)


def scans_over(points: int) -> list[str]:
    """archive/name of every scan of the shared data's scan archives with more than `points` points."""
    names = []
    for archive in SCAN_ARCHIVES:
        with np.load(DATA / f"{archive}.npz") as data:
            shapes = {name: data[name].shape for name in data.files}  # each access reads the array
            names += [f"{archive}/{name}" for name, shape in shapes.items() if len(shape) == 2 and shape[0] > points]
    return names


def pair_set(spec: str, count: int = 25, seed: int = 0, per_scan: int = 1) -> list[Pair]:
    """The pairs a set name stands for: ModelNet `split:noise[:so3][:count]` (`count` pairs unless the
    name counts them), `indoor` or `outdoor` (`:shared` for the paper's pairs; `per_scan` pairs per
    held-out scan), `truth` (the real pairs with ground truth), `scans` (DEFAULT_SCANS' views),
    `scans:N` (a view of every scan of the shared data with more than N points)."""
    parts = spec.split(":")
    if parts[0] in ("indoor", "outdoor"):
        return scene_pairs(parts[0], per_scan, seed=seed, shared=parts[1:] == ["shared"])
    if spec == "truth":
        return truth_pairs()
    if parts[0] == "scans":
        names = DEFAULT_SCANS if len(parts) == 1 else scans_over(int(parts[1]))
        return [scan_pair(name, seed) for name in names]
    if parts[-1].isdigit():
        count = int(parts.pop())
    split, noise, *rest = parts
    return modelnet_pairs(count, split, noise, so3=rest == ["so3"], seed=seed)


# ---------------------------------------------------------------- the classical peers


def open3d_fpfh_ransac_icp(source: np.ndarray, target: np.ndarray, voxel: float, tight: bool = False):
    """Open3D's global-registration tutorial: FPFH + RANSAC on voxel-downsampled clouds, then
    point-to-plane ICP; `tight`: features on the full clouds and point-to-point ICP."""
    import open3d as o3d

    reg, geometry = o3d.pipelines.registration, o3d.geometry

    def cloud(points: np.ndarray, normals: bool) -> "geometry.PointCloud":
        result = geometry.PointCloud(o3d.utility.Vector3dVector(points))
        if normals:
            result.estimate_normals(geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        return result

    def features(full: "geometry.PointCloud"):
        down = full if tight else full.voxel_down_sample(voxel)
        down.estimate_normals(geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        return down, reg.compute_fpfh_feature(down, geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))

    full_source, full_target = cloud(source, False), cloud(target, not tight)
    (down_source, source_fpfh), (down_target, target_fpfh) = features(full_source), features(full_target)
    distance = 1.5 * voxel
    ransac = reg.registration_ransac_based_on_feature_matching(
        down_source,
        down_target,
        source_fpfh,
        target_fpfh,
        True,
        distance,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(100000, 0.999),
    )
    estimation = reg.TransformationEstimationPointToPoint() if tight else reg.TransformationEstimationPointToPlane()
    icp = reg.registration_icp(full_source, full_target, 0.4 * voxel, ransac.transformation, estimation)
    return from_matrix(np.asarray(icp.transformation))


# The peer's GICP runs on every CPU above this many points per cloud; below it one thread was
# faster in this process, right after a network call (1.6 against 2.9 ms on ModelNet pairs).
PEER_THREADED_POINTS = 4_000


def kiss_matcher_gicp(source: np.ndarray, target: np.ndarray, voxel: float):
    """KISS-Matcher's global estimate, refined by small_gicp's GICP, on every CPU for large clouds
    (PEER_THREADED_POINTS)."""
    import kiss_matcher
    import small_gicp

    source, target = np.ascontiguousarray(source, np.float64), np.ascontiguousarray(target, np.float64)
    solution = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel)).estimate(source, target)
    start = to_matrix(np.asarray(solution.rotation), np.asarray(solution.translation))
    result = small_gicp.align(
        target,
        source,
        init_T_target_source=start,
        registration_type="GICP",
        downsampling_resolution=voxel,
        max_correspondence_distance=2 * voxel,
        num_threads=(os.cpu_count() or 1) if min(len(source), len(target)) > PEER_THREADED_POINTS else 1,
    )
    return from_matrix(np.asarray(result.T_target_source))


# ---------------------------------------------------------------- errors and records


def errors(pair: Pair, rotation: np.ndarray, translation: np.ndarray) -> dict:
    """Isotropic errors and the verdict, plus the paper's per-axis errors (Euler angles in degrees,
    translation per axis) whose means and RMS make its tables' MAE and RMSE."""
    rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    paper = registration_errors(rotation[None], translation[None], pair.rotation[None], pair.translation[None])
    rotation_deg, translation_error = float(paper["rotation_deg"][0]), float(paper["translation"][0])
    right = rotation_deg <= RIGHT_ROTATION_DEG and translation_error <= RIGHT_TRANSLATION_SHARE * pair.extent
    return {
        "rotation_deg": rotation_deg,
        "translation": translation_error,
        "right": bool(right),
        "euler_abs_deg": paper["euler_abs"][0].tolist(),
        "translation_abs": paper["trans_abs"][0].tolist(),
    }


def run_header() -> dict:
    return {
        "command": " ".join(["python -m", f"bench.{Path(sys.argv[0]).stem}", *sys.argv[1:]]),
        "when": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpus": os.cpu_count(),
    }


def write_record(path: Path, record: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {path}")
