"""From two user clouds to a rigid transform in the user's units: the one pre/post-processing path.

`register_clouds` validates both clouds, removes exact duplicates (and reports how many),
applies the optional initial guess to the source, resamples each cloud to the network's point
count, centres each and scales both by one common factor to the network's radius
(`model.geometry.NETWORK_RADIUS`), asks the model (any async callable) for the transform between
the normalised clouds, maps it back into the user's units, composes it with the initial guess,
optionally refines it with ICP on the full clouds, and scores it (Open3D-style fitness and
inlier RMSE).
"""

import asyncio
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from model.geometry import (
    Normalisation,
    apply_transform,
    degeneracy,
    fitness_and_rmse,
    from_matrix,
    icp_refine,
    nearest_rotation,
    remove_duplicates,
    resample_indices,
    rigidity_error,
    to_matrix,
)

# ICP's correspondence distance and the fitness threshold, in normalised units (clouds of radius NETWORK_RADIUS):
# 0.05 recovers clean partial pairs exactly, while 0.3 biases the result by about half a degree.
DEFAULT_DISTANCE_NORMALISED = 0.05
# ICP holds the interpreter lock: a subset of each cloud and a time limit keep one refinement from
# stalling the event loop or a worker thread for long (the whole clouds still score the result).
ICP_MAX_POINTS = 50_000
ICP_MAX_SECONDS = 10.0
INIT_RIGIDITY_TOLERANCE = 1e-3  # accepts matrices printed with a few decimals
MAX_COORDINATE = 1e12  # beyond this, squared distances lose all precision (and eventually overflow)

Sampling = Literal["fps", "random"]


class InvalidInput(ValueError):
    """Input that cannot be registered; `field` names the offending part of the request."""

    def __init__(self, field: str, problem: str):
        super().__init__(f"{field}: {problem}")
        self.field = field
        self.problem = problem


class RegistrationFailed(RuntimeError):
    """The model gave no usable transform for valid-looking input (e.g. non-finite numbers)."""


@dataclass(frozen=True)
class Prediction:
    """The model's transform between the normalised clouds, and what it cost."""

    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3], normalised units
    queue_ms: float = 0.0
    inference_ms: float = 0.0
    batch_size: int = 1


Predict = Callable[[np.ndarray, np.ndarray], Awaitable[Prediction]]
RunBlocking = Callable[..., Awaitable[Any]]


@dataclass(frozen=True)
class RefineParams:
    max_distance: float | None = None  # user units; None: DEFAULT_DISTANCE_NORMALISED converted
    max_iterations: int = 30


@dataclass(frozen=True)
class RegistrationParams:
    num_points: int  # points per cloud given to the network
    sampling: Sampling = "fps"
    seed: int = 0
    init: np.ndarray | None = None  # 4x4, applied to the source before the network
    refine: RefineParams | None = None
    fitness_threshold: float | None = None  # user units; None: DEFAULT_DISTANCE_NORMALISED converted
    min_points: int = 32
    max_cloud_points: int = 500_000
    fps_max_input_points: int = 32_768


@dataclass(frozen=True)
class CloudReport:
    received: int
    duplicates_removed: int
    network_points: int
    upsampled: bool  # fewer distinct points than network_points: some were repeated


@dataclass(frozen=True)
class RefineReport:
    max_distance: float
    iterations: int
    network_rotation: np.ndarray  # the transform before refinement
    network_translation: np.ndarray


@dataclass(frozen=True)
class RegistrationResult:
    rotation: np.ndarray  # [3, 3]: target ~ source @ rotation.T + translation
    translation: np.ndarray  # [3], user units
    fitness: float
    inlier_rmse: float
    fitness_threshold: float
    source: CloudReport
    target: CloudReport
    refinement: RefineReport | None
    prediction: Prediction
    preprocess_ms: float
    postprocess_ms: float

    @property
    def transform(self) -> np.ndarray:
        return to_matrix(self.rotation, self.translation)


# ---------------------------------------------------------------- input checks


def as_points(value: Any, field: str) -> np.ndarray:
    """An N x 3 float64 array of finite coordinates from nested lists or an array, or InvalidInput."""
    if isinstance(value, np.ndarray):
        array = value
        if array.dtype.kind not in "fiu":
            raise InvalidInput(field, f"coordinates must be numbers, got an array of {array.dtype}")
    else:
        try:
            array = np.asarray(value)
        except ValueError:  # ragged nesting
            raise InvalidInput(field, _describe_rows(value)) from None
        if array.dtype.kind not in "fiu":
            raise InvalidInput(field, _describe_rows(value))
    if array.size == 0:
        raise InvalidInput(field, "is empty; send a list of [x, y, z] points")
    if array.ndim != 2 or array.shape[1] != 3:
        if array.ndim < 2 and not isinstance(value, np.ndarray):
            raise InvalidInput(field, _describe_rows(value))
        raise InvalidInput(field, f"must be a list of [x, y, z] points (N x 3), got shape {list(array.shape)}")
    if not isinstance(value, np.ndarray) and _has_bool(value):
        raise InvalidInput(field, _describe_rows(value))
    array = array.astype(np.float64, copy=False)
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InvalidInput(
            field,
            f"{len(bad)} point(s) have NaN or infinite coordinates (first at index {bad[0]}: "
            f"{array[bad[0]].tolist()}); drop or repair them before sending",
        )
    if np.abs(array).max() > MAX_COORDINATE:
        raise InvalidInput(field, f"has coordinates beyond ±{MAX_COORDINATE:g}; shift or rescale the cloud first")
    return array


def _has_bool(value: Any) -> bool:
    """Whether N x 3 nested rows hold a true/false, which numpy would quietly read as 1/0 (~15 ms per 100k points)."""
    return any(type(coordinate) is bool for row in value for coordinate in row)


def _describe_rows(value: Any) -> str:
    """Why nested lists are not N x 3 numbers, pointing at the first bad row."""
    if not isinstance(value, Sequence) or isinstance(value, str | bytes):
        return f"must be a list of [x, y, z] points, got {type(value).__name__}"
    for index, row in enumerate(value):
        if not isinstance(row, Sequence) or isinstance(row, str | bytes):
            return f"point {index} must be a list [x, y, z], got {type(row).__name__}"
        if len(row) != 3:
            return f"point {index} has {len(row)} coordinates; every point needs exactly 3 (x, y, z)"
        for coordinate in row:
            if isinstance(coordinate, bool) or not isinstance(coordinate, int | float):
                return f"point {index} has a non-numeric coordinate {coordinate!r}"
            if abs(coordinate) > MAX_COORDINATE:
                return f"point {index} has a coordinate beyond ±{MAX_COORDINATE:g}; shift or rescale the cloud first"
    return "must be a list of [x, y, z] points (N x 3)"


def _only_numbers(value: Any) -> bool:
    if isinstance(value, list | tuple):
        return all(_only_numbers(item) for item in value)
    return isinstance(value, int | float) and not isinstance(value, bool)


def as_rigid_transform(value: Any, field: str = "init") -> np.ndarray:
    """A proper rigid 4x4 matrix (rotation re-orthonormalised), or InvalidInput."""
    if not isinstance(value, np.ndarray) and not _only_numbers(value):  # numpy would read "1" and true as numbers
        raise InvalidInput(field, "must be a 4x4 matrix of numbers (not strings or true/false)")
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise InvalidInput(field, "must be a 4x4 matrix of numbers (a list of 4 rows of 4)") from None
    if matrix.shape != (4, 4):
        raise InvalidInput(field, f"must be a 4x4 matrix, got shape {list(matrix.shape)}")
    if not np.isfinite(matrix).all():
        raise InvalidInput(field, "contains NaN or infinite values")
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: not rigid, and no warning about it
        error = rigidity_error(matrix)
    if not error <= INIT_RIGIDITY_TOLERANCE:
        raise InvalidInput(
            field,
            "is not a rigid transform: its upper-left 3x3 must be a rotation (orthonormal, determinant +1) "
            f"and its last row [0, 0, 0, 1] (deviation {error:.3g}, tolerance {INIT_RIGIDITY_TOLERANCE:g})",
        )
    rotation, translation = from_matrix(matrix)
    if np.abs(translation).max() > MAX_COORDINATE:
        raise InvalidInput(field, f"has a translation beyond ±{MAX_COORDINATE:g}, like the clouds' coordinates")
    return to_matrix(nearest_rotation(rotation), translation)


def check_cloud(points: np.ndarray, field: str, params: RegistrationParams) -> np.ndarray:
    """Size and degeneracy checks; returns the cloud without exact duplicates (first ones kept)."""
    if len(points) > params.max_cloud_points:
        raise InvalidInput(
            field, f"has {len(points)} points, more than the limit of {params.max_cloud_points}; subsample it first"
        )
    if len(points) < params.min_points:
        raise InvalidInput(field, f"has {len(points)} points; at least {params.min_points} distinct points are needed")
    if (reason := degeneracy(points)) is not None:
        problem = "all points are identical" if reason == "identical" else "all points lie on one line"
        raise InvalidInput(field, f"is degenerate: {problem}, so no rigid transform can be determined")
    unique = remove_duplicates(points)
    if len(unique) < params.min_points:
        raise InvalidInput(
            field,
            f"has only {len(unique)} distinct points ({len(points) - len(unique)} exact duplicates); "
            f"at least {params.min_points} are needed",
        )
    return unique


# ---------------------------------------------------------------- the pipeline


def sample_indices(points: np.ndarray, count: int, sampling: Sampling, seed: int, fps_max_input: int) -> np.ndarray:
    """Indices bringing one cloud to exactly `count` points, reproducible from (cloud, seed) alone.

    Farthest-point sampling of very large clouds first takes a seeded random subset of
    fps_max_input points: the result stays deterministic and the cost bounded.
    """
    rng = np.random.default_rng(seed)  # a fresh generator per cloud: the other cloud does not matter
    if sampling == "fps" and len(points) > fps_max_input:
        subset = np.sort(rng.choice(len(points), size=fps_max_input, replace=False))
        return subset[resample_indices(fps_max_input, count, "fps", rng, points[subset])]
    return resample_indices(len(points), count, sampling, rng, points)


@dataclass(frozen=True)
class _Prepared:
    source: np.ndarray  # distinct source points, user units, without init
    target: np.ndarray
    source_network: np.ndarray  # [num_points, 3] float32, normalised, init applied
    target_network: np.ndarray
    normalisation: Normalisation
    init: np.ndarray  # 4x4
    source_report: CloudReport
    target_report: CloudReport
    seconds: float


def _prepare(source: np.ndarray, target: np.ndarray, params: RegistrationParams) -> _Prepared:
    started = time.perf_counter()
    source_unique = check_cloud(source, "source", params)
    target_unique = check_cloud(target, "target", params)
    init = np.eye(4) if params.init is None else params.init
    count = params.num_points
    fps_cap = params.fps_max_input_points
    source_sampled = source_unique[sample_indices(source_unique, count, params.sampling, params.seed, fps_cap)]
    target_sampled = target_unique[sample_indices(target_unique, count, params.sampling, params.seed, fps_cap)]
    source_sampled = apply_transform(source_sampled, *from_matrix(init))
    normalisation = Normalisation(source_sampled, target_sampled)
    return _Prepared(
        source=source_unique,
        target=target_unique,
        source_network=normalisation.source(source_sampled).astype(np.float32),
        target_network=normalisation.target(target_sampled).astype(np.float32),
        normalisation=normalisation,
        init=init,
        source_report=CloudReport(len(source), len(source) - len(source_unique), count, len(source_unique) < count),
        target_report=CloudReport(len(target), len(target) - len(target_unique), count, len(target_unique) < count),
        seconds=time.perf_counter() - started,
    )


def _finish(prepared: _Prepared, prediction: Prediction, params: RegistrationParams) -> RegistrationResult:
    started = time.perf_counter()
    if not (np.isfinite(prediction.rotation).all() and np.isfinite(prediction.translation).all()):
        raise RegistrationFailed("the model returned a non-finite transform for these clouds")
    # The network's transform maps the init-moved source onto the target; compose it with init.
    rotation, translation = prepared.normalisation.to_user_units(
        nearest_rotation(np.asarray(prediction.rotation, np.float64)), np.asarray(prediction.translation, np.float64)
    )
    rotation, translation = from_matrix(to_matrix(rotation, translation) @ prepared.init)
    to_user = 1.0 / prepared.normalisation.scale
    refinement = None
    if params.refine is not None:
        max_distance = params.refine.max_distance or DEFAULT_DISTANCE_NORMALISED * to_user
        network_rotation, network_translation = rotation, translation
        rotation, translation, iterations = icp_refine(
            prepared.source,
            prepared.target,
            rotation,
            translation,
            max_distance,
            params.refine.max_iterations,
            max_points=ICP_MAX_POINTS,
            max_seconds=ICP_MAX_SECONDS,
        )
        rotation = nearest_rotation(rotation)
        refinement = RefineReport(max_distance, iterations, network_rotation, network_translation)
    threshold = params.fitness_threshold or DEFAULT_DISTANCE_NORMALISED * to_user
    fitness, inlier_rmse = fitness_and_rmse(
        apply_transform(prepared.source, rotation, translation), prepared.target, threshold
    )
    return RegistrationResult(
        rotation=rotation,
        translation=translation,
        fitness=fitness,
        inlier_rmse=inlier_rmse,
        fitness_threshold=threshold,
        source=prepared.source_report,
        target=prepared.target_report,
        refinement=refinement,
        prediction=prediction,
        preprocess_ms=prepared.seconds * 1000.0,
        postprocess_ms=(time.perf_counter() - started) * 1000.0,
    )


async def register_clouds(
    source: np.ndarray,
    target: np.ndarray,
    params: RegistrationParams,
    predict: Predict,
    run_blocking: RunBlocking = asyncio.to_thread,
) -> RegistrationResult:
    """Register `source` onto `target` (both N x 3 in user units, already through `as_points`).

    `predict` receives the two normalised float32 clouds [num_points, 3] and returns the
    transform between them (in production: the batcher). The CPU-heavy steps run through
    `run_blocking` (a worker thread by default) so that the event loop keeps serving.
    Raises InvalidInput for clouds that cannot be registered.
    """
    prepared = await run_blocking(_prepare, source, target, params)
    prediction = await predict(prepared.source_network, prepared.target_network)
    return await run_blocking(_finish, prepared, prediction, params)
