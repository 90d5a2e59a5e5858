"""NumPy geometry shared by evaluation, the export checks and the service (imports no torch).

Conventions: points are [N, 3] (or [B, N, 3]) arrays; a rigid transform maps source to target as
target ~ source @ R.T + t; 4x4 matrices are homogeneous [[R, t], [0, 1]].
"""

import time
from collections.abc import Sequence
from functools import cached_property
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

# ---------------------------------------------------------------- rigid transforms


def euler_to_matrix(angles_zyx_deg: np.ndarray) -> np.ndarray:
    """Rotation R = Rx @ Ry @ Rz from angles (z, y, x) in degrees, as the DCP/IFNet protocol."""
    return Rotation.from_euler("zyx", angles_zyx_deg, degrees=True).as_matrix()


def matrix_to_euler(rotation: np.ndarray) -> np.ndarray:
    """Angles (z, y, x) in degrees of rotation matrices [..., 3, 3] (inverse of euler_to_matrix)."""
    return Rotation.from_matrix(rotation).as_euler("zyx", degrees=True)


def apply_transform(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    return points @ np.swapaxes(rotation, -1, -2) + np.expand_dims(translation, -2)


def to_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """[..., 3, 3] and [..., 3] -> homogeneous [..., 4, 4]."""
    out = np.zeros((*rotation.shape[:-2], 4, 4), dtype=np.float64)
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def from_matrix(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return transform[..., :3, :3], transform[..., :3, 3]


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The proper rotation closest (Frobenius) to a 3x3 matrix: removes float drift from R."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def rigidity_error(transform: np.ndarray) -> float:
    """How far a 4x4 matrix is from a proper rigid transform (0 for an exact one)."""
    rotation = transform[:3, :3]
    orthogonality = np.abs(rotation @ rotation.T - np.eye(3)).max()
    return float(max(orthogonality, abs(np.linalg.det(rotation) - 1.0), np.abs(transform[3] - [0, 0, 0, 1]).max()))


def random_rotation(rng: np.random.Generator, max_angle_deg: float = 45.0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's rotation: Euler angles (z, y, x) each uniform in [0, max]; returns (R, angles)."""
    angles = rng.uniform(0.0, max_angle_deg, size=3)
    return euler_to_matrix(angles), angles


# ---------------------------------------------------------------- error metrics


def rotation_angle_deg(rotation_a: np.ndarray, rotation_b: np.ndarray) -> np.ndarray:
    """Isotropic angle in degrees between rotations [..., 3, 3] (accurate near zero)."""
    difference = np.linalg.norm((rotation_a - rotation_b).reshape(*rotation_a.shape[:-2], 9), axis=-1)
    return np.degrees(2.0 * np.arcsin(np.clip(difference / (2.0 * np.sqrt(2.0)), 0.0, 1.0)))


def registration_errors(
    rot_pred: np.ndarray, trans_pred: np.ndarray, rot_true: np.ndarray, trans_true: np.ndarray
) -> dict[str, np.ndarray]:
    """Per-pair errors for batches [B, 3, 3] / [B, 3].

    euler_abs: |Euler(R_pred) - Euler(R_true)| per angle (deg), the anisotropic metric of DCP;
    trans_abs: |t_pred - t_true| per axis; rotation_deg / translation: isotropic errors.
    """
    euler_diff = matrix_to_euler(rot_pred) - matrix_to_euler(rot_true)
    euler_diff = (euler_diff + 180.0) % 360.0 - 180.0  # wrap, so 359 vs 1 degree is 2 degrees
    return {
        "euler_abs": np.abs(euler_diff),
        "trans_abs": np.abs(trans_pred - trans_true),
        "rotation_deg": rotation_angle_deg(rot_pred, rot_true),
        "translation": np.linalg.norm(trans_pred - trans_true, axis=-1),
    }


def summarise_errors(errors: dict[str, np.ndarray]) -> dict[str, float]:
    """The paper's table (RMSE/MAE of Euler angles and translation) plus isotropic errors and recall."""
    rot, trans = errors["rotation_deg"], errors["translation"]
    return {
        "rmse_r": float(np.sqrt(np.mean(errors["euler_abs"] ** 2))),
        "mae_r": float(np.mean(errors["euler_abs"])),
        "rmse_t": float(np.sqrt(np.mean(errors["trans_abs"] ** 2))),
        "mae_t": float(np.mean(errors["trans_abs"])),
        "iso_r_mean": float(np.mean(rot)),
        "iso_r_median": float(np.median(rot)),
        "iso_t_mean": float(np.mean(trans)),
        "recall_1deg_001": float(np.mean((rot < 1.0) & (trans < 0.01))),
        "recall_5deg_005": float(np.mean((rot < 5.0) & (trans < 0.05))),
    }


def fitness_and_rmse(source_aligned: np.ndarray, target: np.ndarray, threshold: float) -> tuple[float, float]:
    """Open3D-style fitness (share of source points with a target point within threshold) and
    the RMSE of those inlier distances."""
    distances, _ = cKDTree(target).query(source_aligned, k=1, distance_upper_bound=threshold)
    inliers = np.isfinite(distances)
    if not inliers.any():
        return 0.0, 0.0
    return float(inliers.mean()), float(np.sqrt(np.mean(distances[inliers] ** 2)))


# ---------------------------------------------------------------- sampling and normalisation


DEDUPE_KEY = (np.sqrt(3.0), np.sqrt(5.0))  # irrational weights: distinct rows rarely share a key


def remove_duplicates(points: np.ndarray) -> np.ndarray:
    """Drop exact duplicate points, keeping first occurrences in their original order (`points`
    itself when it has none).

    Duplicates make kNN ties, whose order differs between torch and ONNX Runtime. Rows are equal
    as numbers (-0.0 is 0.0). Equal rows share one key (elementwise arithmetic rounds alike for
    every row), so one sort of the keys finds the few rows that may repeat; a stable lexicographic
    sort of those puts each point's copies together, first occurrence first (several times faster
    than sorting every row lexicographically, which is itself faster than np.unique(axis=0)).
    """
    key = points[:, 0] + points[:, 1] * DEDUPE_KEY[0] + points[:, 2] * DEDUPE_KEY[1]
    ordered_keys = np.sort(key)
    shared = np.unique(ordered_keys[1:][ordered_keys[1:] == ordered_keys[:-1]])  # keys of two rows or more
    if not len(shared):
        return points
    candidates = np.flatnonzero(np.isin(key, shared))  # every repeated row among them, in input order
    rows = points[candidates]
    order = np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))
    ordered = rows[order]
    repeats = (ordered[1:] == ordered[:-1]).all(axis=1)  # [M - 1]: row i + 1 equals row i
    keep = np.ones(len(points), dtype=bool)
    keep[candidates[order[1:][repeats]]] = False
    return points[keep]


def degeneracy(points: np.ndarray, relative_tolerance: float = 1e-4) -> str | None:
    """Why a cloud [N, 3] cannot constrain a rigid transform, or None if it can.

    "identical": all points coincide (up to float rounding); "collinear": the second principal
    extent is below relative_tolerance times the first. Coplanar clouds pass: a plane still
    fixes most of the motion, and flat scans are common.
    """
    if len(points) < 2:
        return "identical"
    extents = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)  # largest first
    rounding = 1e-12 * max(float(np.abs(points).max()), 1.0) * np.sqrt(len(points))
    if extents[0] <= rounding:
        return "identical"
    if extents[1] <= relative_tolerance * extents[0]:
        return "collinear"
    return None


class FarthestPoints:
    """Deterministic farthest-point sampling of one cloud that a larger count extends: the first k
    points of a longer sample are the k-point sample, so a second count costs only what it adds."""

    def __init__(self, points: np.ndarray, start: int = 0):
        # Coordinates as contiguous rows and buffers reused every step: few numpy calls per step (their
        # overhead dominates on small clouds). In float32 about the centre: half the memory traffic of
        # float64 (twice as fast on large clouds), and map coordinates keep their precision.
        self.columns = np.ascontiguousarray((points - points.mean(axis=0)).T, dtype=np.float32)  # [3, N]
        self.chosen = [start]
        self.distance = np.full(len(points), np.inf, dtype=np.float32)  # squared, to the nearest chosen
        self.offsets, self.squared = np.empty_like(self.columns), np.empty_like(self.columns[0])

    def first(self, count: int) -> np.ndarray:
        """Indices of the first `count` points chosen."""
        columns, chosen, distance = self.columns, self.chosen, self.distance
        offsets, squared = self.offsets, self.squared
        while len(chosen) < count:
            np.square(np.subtract(columns, columns[:, chosen[-1], None], out=offsets), out=offsets)
            np.add(np.add(offsets[0], offsets[1], out=squared), offsets[2], out=squared)
            np.minimum(distance, squared, out=distance)
            chosen.append(int(distance.argmax()))
        return np.array(chosen[:count], dtype=np.int64)


def farthest_point_sample(points: np.ndarray, count: int, start: int = 0) -> np.ndarray:
    """Indices of `count` points chosen by deterministic farthest-point sampling."""
    return FarthestPoints(points, start).first(count)


def at_most(cloud: np.ndarray, count: int) -> np.ndarray:
    """The cloud farthest-point sampled down to `count` points, or whole if it has no more."""
    return cloud[farthest_point_sample(cloud, count)] if len(cloud) > count else cloud


def exactly(cloud: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """The cloud brought to `count` points as the service brings it (its default seed): farthest-point
    sampled when larger, every point once and seeded random ones repeated when smaller."""
    return cloud[resample_indices(len(cloud), count, "fps", np.random.default_rng(seed), cloud)]


def resample_indices(
    num_points: int,
    count: int,
    method: str,
    rng: np.random.Generator,
    points: np.ndarray,
    farthest: FarthestPoints | None = None,
) -> np.ndarray:
    """Indices that bring a cloud of num_points to exactly count points.

    Larger clouds are subsampled ("fps": farthest point, extending `farthest` when given, "random":
    seeded, without replacement); smaller ones keep every point once and repeat randomly chosen ones
    to fill up. A cloud of exactly count points is kept as it is: any sampling would only reorder it.
    """
    if num_points == count:
        return np.arange(count)
    if num_points > count:
        if method == "fps":
            return (farthest or FarthestPoints(points)).first(count)
        return np.sort(rng.choice(num_points, size=count, replace=False))
    extra = rng.choice(num_points, size=count - num_points, replace=True)
    return np.concatenate([np.arange(num_points), extra])


def cell_keys(cells: np.ndarray) -> np.ndarray:
    """One int64 key per row of non-negative integer cells [N, 3]: equal for equal rows and ordered as
    the rows sort. Several times faster to sort than the rows; where a packed key would overflow, the
    rows' rank among the distinct rows."""
    span = cells.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:
        return np.unique(cells, axis=0, return_inverse=True)[1].ravel()
    return (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]


def voxel_downsample(points: np.ndarray, size: float) -> np.ndarray:
    """One point per occupied cube of side `size`: the centroid of the points inside it."""
    cells = np.floor((points - points.min(axis=0)) / size).astype(np.int64)
    _, cell, counts = np.unique(cell_keys(cells), return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(cell, weights=points[:, axis], minlength=len(counts)) for axis in range(3)], axis=1)
    return sums / counts[:, None]


def crop_nearest(points: np.ndarray, anchor: np.ndarray, count: int) -> np.ndarray:
    """The `count` points nearest to anchor (the protocol's partial view), nearest first."""
    order = np.argsort(np.sum((points - anchor) ** 2, axis=1), kind="stable")
    return points[order[:count]]


def disjoint_halves(points: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two random halves of a cloud without a common point: one surface sampled twice, as when a
    scene is scanned again (the clouds a registration service gets, unlike the protocol's pairs)."""
    order = rng.permutation(len(points))
    return points[order[: len(points) // 2]], points[order[len(points) // 2 :]]


# The network is scale-sensitive (kNN edges, descriptors): user clouds are scaled to the median
# radius of its training crops (768-point crops of unit-sphere shapes, measured from their centroid).
NETWORK_RADIUS = 1.07


class Normalisation:
    """Centre each cloud on its centroid and scale both by one common factor to `radius`.

    The network then sees clouds like its training data; `to_user_units` maps a transform found
    on the normalised clouds back to the original coordinates.
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, radius: float = NETWORK_RADIUS):
        self.source_centre = source.mean(axis=0)
        self.target_centre = target.mean(axis=0)
        furthest = max(
            np.linalg.norm(source - self.source_centre, axis=1).max(),
            np.linalg.norm(target - self.target_centre, axis=1).max(),
        )
        self.scale = radius / furthest if furthest > 0 else 1.0

    def source(self, points: np.ndarray) -> np.ndarray:
        return (points - self.source_centre) * self.scale

    def target(self, points: np.ndarray) -> np.ndarray:
        return (points - self.target_centre) * self.scale

    def to_user_units(self, rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R, t') on normalised clouds -> (R, t) on the original ones.

        s(y - cy) = R s(x - cx) + t'  =>  y = R x + (cy - R cx + t' / s).
        """
        return rotation, self.target_centre - rotation @ self.source_centre + translation / self.scale


# ---------------------------------------------------------------- refinement


# small_gicp holds the interpreter lock while it runs: bounded callers run it a few iterations at a time.
ITERATIONS_PER_CALL = 2


def principal_axes(points: np.ndarray) -> np.ndarray:
    """The cloud's principal axes as the columns of a rotation, least spread first."""
    return np.linalg.eigh(np.cov(points.T))[1]


def extent(points: np.ndarray) -> float:
    """The cloud's size: the diagonal of its bounding box."""
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def slides(
    translation: np.ndarray, target: np.ndarray, shares: Sequence[float], diagonal_shares: Sequence[float] = ()
) -> list[np.ndarray]:
    """`translation` shifted by each share of the target's extent, both ways along each principal
    axis of the target, and by each diagonal share along the four diagonals between each two
    axes: where an answer slid beside the truth would lie."""
    size, axes = extent(target), principal_axes(target).T
    along = [sign * axis for axis in axes for sign in (1.0, -1.0)]
    pairs = ((0, 1), (0, 2), (1, 2))
    between = [
        (one * axes[a] + two * axes[b]) / np.sqrt(2.0) for a, b in pairs for one in (1.0, -1.0) for two in (1.0, -1.0)
    ]

    def shifted(steps: Sequence[float], directions: list[np.ndarray]) -> list[np.ndarray]:
        return [translation + step * size * direction for step in steps for direction in directions]

    return shifted(shares, along) + shifted(diagonal_shares, between)


def subset(points: np.ndarray, count: int) -> np.ndarray:
    """At most `count` of the points: a seeded random subset, in their original order."""
    if len(points) <= count:
        return points
    return points[np.sort(np.random.default_rng(0).choice(len(points), size=count, replace=False))]


# ---------------------------------------------------------------- verification


def point_spacing(points: np.ndarray, max_queries: int = 4096, seed: int = 0, threads: int = 1) -> float:
    """Median distance from a point to its nearest other point: the cloud's sampling step.

    At most max_queries points (a seeded random subset) are queried against the whole cloud, so
    the cost stays bounded on large scans; exact duplicates are not counted as neighbours.
    """
    import small_gicp  # its kd-tree: the same distances as scipy's, built and searched on `threads`

    if len(points) < 2:
        return 0.0
    points = np.ascontiguousarray(points, dtype=np.float64)
    queries = points
    if len(points) > max_queries:
        queries = points[np.random.default_rng(seed).choice(len(points), size=max_queries, replace=False)]
    _, squared = small_gicp.KdTree(points, num_threads=threads).batch_knn_search(queries, 2, num_threads=threads)
    nearest = np.sqrt(squared[:, 1])
    nearest = nearest[nearest > 0]  # duplicates say nothing about the spacing
    return float(np.median(nearest)) if len(nearest) else 0.0


# Calibrated by bench/calibrate_check.py on ModelNet and real-scan pairs with known truth (docs/verification.md).
INLIER_SPACINGS = 1.5  # inlier distance, in point spacings
REFINE_SPACINGS = 2.0  # correspondence distance of refine(), in point spacings
MIN_FITNESS = 0.3  # both ways: below it the clouds hardly touch, and a refinement finds nothing to move
MAX_DRIFT_SPACINGS = 0.2  # a right answer is where refine() settles; wrong ones slide on
MIN_CONSTRAINT = 0.02  # inliers on one plane or one cylinder can slide along it without losing fit
MIN_INLIERS = 30  # fewer matching points prove nothing
SCORE_NORMAL_NEIGHBOURS = 12  # the target's normals of the constraint: the least-spread axis of this many points
CHECK_REFINE_SECONDS = 10.0  # the check's refinement stops here at the latest
# A source point with no other within this many point spacings is an outlier or a lone sample: whether
# it matches tells nothing of how much of the surfaces overlap (AlignmentClouds.surface_fitness).
ISOLATED_SPACINGS = 3.0


class AlignmentScore(NamedTuple):
    """How well a transform lays the source on the target, at an inlier distance set by the spacing."""

    spacing: float  # the larger of the two clouds' point spacings (point_spacing)
    threshold: float  # inlier distance: INLIER_SPACINGS * spacing
    fitness: float  # share of source points with a target point within threshold
    inlier_rmse: float  # RMSE of those distances
    overlap: float  # share of target points with a moved source point within threshold (the other way)
    inliers: int  # source points within threshold
    constraint: float  # how well the inliers pin all six motions down (0: they can slide; see inlier_constraint)


def inlier_constraint(points: np.ndarray, normals: np.ndarray) -> float:
    """Smallest eigenvalue of the point-to-plane information matrix of unit normals at points.

    Positions are centred and scaled to unit RMS radius, so the value depends on shape alone: 0
    when some motion (a slide along a plane, a turn about an axis of symmetry) moves no point off
    its surface, about 0.1 for points spread over surfaces facing every way.
    """
    if len(points) < 6:
        return 0.0
    centred = points - points.mean(axis=0)
    radius = np.sqrt(np.mean(np.sum(centred**2, axis=1)))
    if radius == 0:
        return 0.0
    jacobian = np.concatenate([np.cross(centred / radius, normals), normals], axis=1)
    return float(np.linalg.eigvalsh(jacobian.T @ jacobian / len(points))[0])


class Verdict(NamedTuple):
    verified: bool
    reason: str | None  # why not, when verified is False


def missed(score: AlignmentScore, min_fitness: float = MIN_FITNESS) -> str | None:
    """Why the score fails whatever its drift: too few matching points, or too little overlap (below
    `min_fitness` either way)."""
    if score.inliers < MIN_INLIERS:
        return f"only {score.inliers} points match within {score.threshold:.3g}"
    if min(score.fitness, score.overlap) < min_fitness:
        return (
            f"low overlap: fitness {score.fitness:.2f}, reverse {score.overlap:.2f} (at least {min_fitness:g} needed)"
        )
    return None


def judge(score: AlignmentScore, drift: float) -> Verdict:
    """The verdict on a score and its drift (how far refine() moves the answer, in point spacings).

    Every rule is one failure mode of a wrong answer; a right answer passes all of them, a right
    answer a refinement would still improve may be flagged (flagging it is the safe error).
    """
    if (reason := missed(score)) is not None:
        return Verdict(False, reason)
    if score.constraint < MIN_CONSTRAINT:
        return Verdict(False, f"the matching points do not pin the motion down (constraint {score.constraint:.3f})")
    if not drift <= MAX_DRIFT_SPACINGS:
        return Verdict(False, f"not settled: refinement moves the points {drift:.2f} point spacings")
    return Verdict(True, None)


class Verification(NamedTuple):
    verified: bool
    reason: str | None
    score: AlignmentScore
    drift: float | None  # RMS move of the source points under refine(), in point spacings; None for a miss

    @property
    def unpinned(self) -> bool:
        """Failed on the constraint alone: the answer fits and has settled, but the matching points
        would let it slide (a plane with little on it), so the clouds cannot tell it from its neighbours."""
        if self.verified or self.drift is None:
            return False
        return judge(self.score._replace(constraint=MIN_CONSTRAINT), self.drift).verified


def verify_alignment(
    source: np.ndarray,
    target: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    spacing: float | None = None,
) -> Verification:
    """Is (R, t) right? AlignmentClouds.verify on one pair."""
    return AlignmentClouds(source, target, spacing).verify(rotation, translation)


# ---------------------------------------------------------------- refinement (spacing-based)


def refine(
    source: np.ndarray,
    target: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    max_distance: float | None = None,
    method: str = "GICP",
    max_iterations: int = 30,
    spacing: float | None = None,
    max_seconds: float | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """small_gicp registration of one pair from (rotation, translation): AlignmentClouds.refine."""
    return AlignmentClouds(source, target, spacing).refine(
        rotation, translation, max_distance, method, max_iterations, max_seconds
    )


class GicpClouds(NamedTuple):
    """small_gicp's objects of one pair (that module is imported only where they are built)."""

    source: object  # small_gicp.PointCloud with normals and covariances
    target: object  # small_gicp.PointCloud with normals and covariances
    target_tree: object  # small_gicp.KdTree of the target


class AlignmentClouds:
    """One pair's clouds made ready once for every refinement and check of its answers: the point
    spacing, scipy's kd-tree of the target (scores), and small_gicp's clouds with their normals and
    covariances and its kd-tree of the target (refinement; the target's normals also give scores
    their constraint). Never changed after construction (but for the source's centre and surface and
    the target's centre, axes and extent, computed once when first asked), so threads may share it;
    building it takes about as long as a few GICP iterations. small_gicp runs on `threads` OpenMP
    threads (it holds the interpreter lock while it runs, so more threads are the only way its work
    uses more than one CPU)."""

    def __init__(self, source: np.ndarray, target: np.ndarray, spacing: float | None = None, threads: int = 1):
        import small_gicp  # imported here so that the rest of this module needs only numpy/scipy

        self.source = np.ascontiguousarray(source, dtype=np.float64)
        self.target = np.ascontiguousarray(target, dtype=np.float64)
        self.threads = threads
        if spacing is None:
            spacing = max(point_spacing(cloud, threads=threads) for cloud in (self.source, self.target))
        self.spacing = spacing
        self.target_tree = cKDTree(self.target)
        # small_gicp's clouds are each centred: it turns the source about its origin, and far from
        # it (map coordinates, or a sensor's frame against a map's) the turns lose precision and
        # answers failed the check.
        self.centres = [points.min(axis=0) / 2 + points.max(axis=0) / 2 for points in (self.source, self.target)]
        clouds = [
            small_gicp.PointCloud(points - centre)
            for points, centre in zip((self.source, self.target), self.centres, strict=True)
        ]
        trees = [small_gicp.KdTree(cloud, num_threads=threads) for cloud in clouds]
        # The constraint's normals come from fewer neighbours than GICP's covariances: its calibration's.
        small_gicp.estimate_normals(clouds[1], trees[1], num_neighbors=SCORE_NORMAL_NEIGHBOURS, num_threads=threads)
        self.target_normals = np.array(clouds[1].normals()[:, :3])  # a copy: the next call overwrites them
        for cloud, tree in zip(clouds, trees, strict=True):
            small_gicp.estimate_normals_covariances(cloud, tree, num_neighbors=20, num_threads=threads)
        self.gicp = GicpClouds(clouds[0], clouds[1], trees[1])

    def score(self, rotation: np.ndarray, translation: np.ndarray) -> AlignmentScore:
        """Fitness and inlier RMSE of (R, t) at INLIER_SPACINGS point spacings, both ways, and how
        well the inliers constrain the motion."""
        threshold = INLIER_SPACINGS * self.spacing
        moved = apply_transform(self.source, rotation, translation)
        forward, matches = self.target_tree.query(moved, k=1, distance_upper_bound=threshold)
        backward, _ = cKDTree(moved).query(self.target, k=1, distance_upper_bound=threshold)
        inliers = np.isfinite(forward)
        matched_index = matches[inliers]
        matched, normals = self.target[matched_index], self.target_normals[matched_index]
        return AlignmentScore(
            spacing=float(self.spacing),
            threshold=float(threshold),
            fitness=float(inliers.mean()),
            inlier_rmse=float(np.sqrt(np.mean(forward[inliers] ** 2))) if inliers.any() else 0.0,
            overlap=float(np.isfinite(backward).mean()),
            inliers=int(inliers.sum()),
            constraint=inlier_constraint(matched, normals) if len(matched) else 0.0,
        )

    def fitness(self, points: np.ndarray, rotation: np.ndarray, translation: np.ndarray, spacings: float) -> float:
        """The share of `points` (some of the source's, e.g. a subset) moved by (R, t) with a target
        point within `spacings` point spacings: score's fitness, cheap enough to rank many coarse answers."""
        moved = apply_transform(points, rotation, translation)
        distances, _ = self.target_tree.query(moved, k=1, distance_upper_bound=spacings * self.spacing)
        return float(np.isfinite(distances).mean())

    @cached_property
    def source_centre(self) -> np.ndarray:
        return self.source.mean(axis=0)

    @cached_property
    def target_centre(self) -> np.ndarray:
        return self.target.mean(axis=0)

    @cached_property
    def target_axes(self) -> np.ndarray:
        """principal_axes of the target."""
        return principal_axes(self.target)

    @cached_property
    def target_extent(self) -> float:
        return extent(self.target)

    def centres_apart(self, first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray]) -> float:
        """How far apart two poses (R, t) put the source's centre, as a share of the target's extent."""
        (rotation, translation), (other_rotation, other_translation) = first, second
        apart = (rotation - other_rotation) @ self.source_centre + translation - other_translation
        return float(np.linalg.norm(apart)) / self.target_extent

    def surface_fitness(self, rotation: np.ndarray, translation: np.ndarray) -> float:
        """score's fitness over the source's surface points alone (those with another source point within
        ISOLATED_SPACINGS): the share of the source's surfaces that (R, t) lays on the target's. The
        fitness itself where no point has a neighbour."""
        return self.fitness(self.source_surface, rotation, translation, INLIER_SPACINGS)

    @cached_property
    def source_surface(self) -> np.ndarray:
        """The source's points with another within ISOLATED_SPACINGS, or all of them where none has."""
        nearest, _ = cKDTree(self.source).query(self.source, k=2, distance_upper_bound=ISOLATED_SPACINGS * self.spacing)
        surface = self.source[np.isfinite(nearest[:, 1])]
        return surface if len(surface) else self.source

    def verify(self, rotation: np.ndarray, translation: np.ndarray, min_fitness: float = MIN_FITNESS) -> Verification:
        """Is (R, t) right? Scores it at the clouds' point spacing, refines it once to see whether it
        has settled, and judges both (judge). Call it on the final answer, refined or not. A score
        that fails on its own (missed, at `min_fitness`) is not refined: where it would settle cannot
        save it."""
        score = self.score(rotation, translation)
        if (reason := missed(score, min_fitness)) is not None:
            return Verification(False, reason, score, None)
        refined_rotation, refined_translation, _ = self.refine(rotation, translation, max_seconds=CHECK_REFINE_SECONDS)
        moved = apply_transform(self.source, rotation, translation)
        shift = apply_transform(self.source, refined_rotation, refined_translation) - moved
        spacing = self.spacing
        drift = float(np.sqrt(np.mean(np.sum(shift**2, axis=1))) / spacing) if spacing > 0 else float("inf")
        verdict = judge(score, drift)
        return Verification(verdict.verified, verdict.reason, score, drift)

    def refine(
        self,
        rotation: np.ndarray,
        translation: np.ndarray,
        max_distance: float | None = None,
        method: str = "GICP",
        max_iterations: int = 30,
        max_seconds: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """small_gicp registration (GICP by default) of the whole clouds from (rotation, translation).

        max_distance: the correspondence distance in the clouds' units; by default REFINE_SPACINGS
        point spacings. method: small_gicp's "GICP", "PLANE_ICP" or "ICP". Returns the refined
        (R, t) and the number of iterations run.

        small_gicp holds the interpreter lock while it runs, so a caller that shares the process
        with other work (the service) passes `max_seconds`: the iterations then run a few at a
        time, between which other threads get the lock and after which the refinement may end.
        """
        import small_gicp

        if max_distance is None:
            max_distance = REFINE_SPACINGS * self.spacing
        clouds = self.gicp
        step = max_iterations if max_seconds is None else ITERATIONS_PER_CALL
        source_centre, target_centre = self.centres
        transform = to_matrix(rotation, translation + rotation @ source_centre - target_centre)  # of the centred clouds
        steps = 0  # small_gicp numbers its steps from 0 and reports the last one's number
        started = time.perf_counter()
        while steps < max_iterations:
            result = small_gicp.align(
                clouds.target,
                clouds.source,
                clouds.target_tree,
                init_T_target_source=transform,
                registration_type=method,
                max_correspondence_distance=max_distance,
                num_threads=self.threads,
                max_iterations=min(step, max_iterations - steps),
                rotation_epsilon=1e-5,
                translation_epsilon=1e-6 * max_distance,
            )
            transform = np.asarray(result.T_target_source)
            steps += int(result.iterations) + 1
            if result.converged or (max_seconds is not None and time.perf_counter() - started > max_seconds):
                break
        refined_rotation, refined_translation = from_matrix(transform)
        refined_rotation = nearest_rotation(refined_rotation)
        return refined_rotation, refined_translation - refined_rotation @ source_centre + target_centre, steps - 1


# ---------------------------------------------------------------- feature-based global registration

FEATURE_VOXEL_SPACINGS = 1.5  # KISS-Matcher's voxel size, in point spacings
FEATURE_VOXEL = 0.05  # the clouds are scaled so that the voxel is this: KISS-Matcher refuses tiny voxels
FEATURE_MAX_VOXELS = 2**19  # half of KISS-Matcher's voxel key range (21 bits per axis) from the origin
# KISS-Matcher kills the process (a segfault, not an exception) on a cloud where at most a few voxels
# have the 3 voxels within its normal radius that a feature needs: points in isolated clumps, such as
# pairs of near-duplicates far apart (their spacing, and so the voxel, is the clumps' size). It crashed
# here on clouds with 0-2 such voxels; a cloud reaches it only with FEATURE_MIN_DESCRIBED of them,
# counted on voxel centres (every cloud of the benchmarks has at least 30).
FEATURE_NORMAL_VOXELS = 3.0  # KISS-Matcher's normal radius, in voxels (its default configuration)
FEATURE_MIN_DESCRIBED = 8
# Voxels looked at: a few first (on a scan's surface nearly every voxel is describable), then more.
FEATURE_DESCRIBED_SAMPLES = (64, 1_000)


def occupied_voxels(points: np.ndarray, voxel: float) -> np.ndarray:
    """The distinct voxels (of side `voxel`) holding the points, as integer coordinates in voxel units."""
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    return cells[np.unique(cell_keys(cells), return_index=True)[1]]


def describable(points: np.ndarray, voxel: float) -> bool:
    """The cloud has at least FEATURE_MIN_DESCRIBED voxels (of side `voxel`) with two other occupied
    voxels whose centres lie within FEATURE_NORMAL_VOXELS of their own: enough for KISS-Matcher."""
    keys = occupied_voxels(points, voxel)
    if len(keys) < FEATURE_MIN_DESCRIBED:
        return False
    tree, order = cKDTree(keys), np.random.default_rng(0).permutation(len(keys))
    for count in FEATURE_DESCRIBED_SAMPLES:
        distances, _ = tree.query(keys[order[:count]], k=3, distance_upper_bound=FEATURE_NORMAL_VOXELS)
        if np.isfinite(distances[:, 2]).sum() >= FEATURE_MIN_DESCRIBED:
            return True
    return False


def feature_match(
    source: np.ndarray, target: np.ndarray, spacing: float, spacings: float = FEATURE_VOXEL_SPACINGS
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) from matching local features (KISS-Matcher) on a voxel of `spacings` point spacings,
    whatever the rotation: a coarse answer to refine. Identity where the matcher finds nothing (the
    answer's check then fails)."""
    import kiss_matcher  # imported here so that the rest of this module needs only numpy/scipy

    scale = FEATURE_VOXEL / (spacings * spacing) if spacing > 0 else 1.0
    reach = FEATURE_MAX_VOXELS * FEATURE_VOXEL / scale  # the farthest a point may lie from the origin

    def beyond(cloud: np.ndarray, offset: np.ndarray) -> bool:
        return bool(np.abs(cloud - offset).max() > reach)

    # Clouds beyond the matcher's voxel keys (map coordinates) are moved by the target's centre: out
    # there it drops points and could crash the process. Only those: its answers change with the
    # clouds' placement, and moving real scans lost some of them. A source still out of reach (the
    # clouds far apart, e.g. one in a sensor's frame, one in a map's) is moved by its own centre.
    offsets = [np.zeros(3), np.zeros(3)]
    if beyond(source, offsets[0]) or beyond(target, offsets[1]):
        offsets = [target.mean(axis=0)] * 2
        if beyond(source, offsets[0]):
            offsets[0] = source.mean(axis=0)
    clouds = []
    for cloud, offset in zip((source, target), offsets, strict=True):
        moved = cloud - offset
        moved = moved[np.abs(moved).max(axis=1) <= reach]  # stray points no key reaches, if any
        scaled = np.ascontiguousarray(moved * scale, np.float64)
        if len(scaled) == 0 or not describable(scaled, FEATURE_VOXEL):
            return np.eye(3), np.zeros(3)
        clouds.append(scaled)
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(FEATURE_VOXEL))
    try:
        found = matcher.estimate(*clouds)
    except RuntimeError:  # the matcher's own refusals (too few points or features)
        return np.eye(3), np.zeros(3)
    rotation, translation = np.asarray(found.rotation, np.float64), np.asarray(found.translation, np.float64)
    if not (np.isfinite(rotation).all() and np.isfinite(translation).all()):
        return np.eye(3), np.zeros(3)
    rotation = nearest_rotation(rotation)
    # target - offsets[1] ~ rotation @ (source - offsets[0]) + translation / scale
    return rotation, translation.reshape(3) / scale + offsets[1] - rotation @ offsets[0]
