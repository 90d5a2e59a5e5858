"""From two user clouds to a rigid transform in the user's units: the one pre/post-processing path.

`register_clouds` checks both clouds, removes exact duplicates (and reports how many), applies
the optional initial guess to the source, resamples each cloud to the network's point count,
centres each and scales both by one common factor to the network's radius
(`model.geometry.NETWORK_RADIUS`), asks the model (any async callable) for the transform between
the normalised clouds, maps it back into the user's units, composes it with the initial guess,
optionally refines it with ICP on the full clouds, and scores it (Open3D-style fitness and
inlier RMSE). `register_pairs` runs a request's pairs through it and the shared batcher.
"""

import asyncio
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from starlette.requests import Request

from model.geometry import (
    Normalisation,
    apply_transform,
    fitness_and_rmse,
    from_matrix,
    icp_refine,
    nearest_rotation,
    resample_indices,
    to_matrix,
)
from service.batcher import Prediction, RequestTimeoutError
from service.schemas import RegistrationOptions, Sampling
from service.settings import Settings
from service.state import ServiceState
from service.validation import InvalidInput, check_cloud

# ICP's correspondence distance and the fitness threshold, in normalised units (clouds of radius NETWORK_RADIUS):
# 0.05 recovers clean partial pairs exactly, while 0.3 biases the result by about half a degree.
DEFAULT_DISTANCE_NORMALISED = 0.05
# ICP holds the interpreter lock: a subset of each cloud and a time limit keep one refinement from
# stalling the event loop or a worker thread for long (the whole clouds still score the result).
ICP_MAX_POINTS = 50_000
ICP_MAX_SECONDS = 10.0

T = TypeVar("T")
Predict = Callable[[np.ndarray, np.ndarray], Awaitable[Prediction]]
RunBlocking = Callable[..., Awaitable[Any]]


class RegistrationFailed(RuntimeError):
    """The model gave no usable transform for valid-looking input (e.g. non-finite numbers)."""


class ClientDisconnected(Exception):
    """The client went away before its answer was ready."""


@dataclass(frozen=True)
class CloudReport:
    received: int
    duplicates_removed: int
    network_points: int
    upsampled: bool  # fewer distinct points than network_points: some were repeated


@dataclass(frozen=True)
class CloudReports:
    source: CloudReport
    target: CloudReport


@dataclass(frozen=True)
class RefineReport:
    max_distance: float
    iterations: int
    network_transform: np.ndarray  # 4x4, before refinement


@dataclass(frozen=True)
class RegistrationResult:
    """One pair's answer, named as the response (`schemas.RegisterResponse`) names it."""

    rotation: np.ndarray  # [3, 3]: target ~ source @ rotation.T + translation
    translation: np.ndarray  # [3], user units
    fitness: float
    inlier_rmse: float
    fitness_threshold: float
    points: CloudReports
    refinement: RefineReport | None
    timings_ms: dict[str, float]  # queue, inference, preprocess, postprocess; batch_size

    @property
    def transform(self) -> np.ndarray:
        return to_matrix(self.rotation, self.translation)


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
    source_network: np.ndarray  # [network_points, 3] float32, normalised, init applied
    target_network: np.ndarray
    normalisation: Normalisation
    init: np.ndarray  # 4x4
    points: CloudReports
    seconds: float


def _prepare(source: np.ndarray, target: np.ndarray, options: RegistrationOptions, settings: Settings) -> _Prepared:
    started = time.perf_counter()
    count = options.network_points
    assert count is not None, "register_pairs resolves the network's point count"
    clouds, sampled, reports = {}, {}, {}
    for name, points in (("source", source), ("target", target)):
        unique = check_cloud(points, name, settings.min_points, settings.max_cloud_points)
        indices = sample_indices(unique, count, options.sampling, options.seed, settings.fps_max_input_points)
        clouds[name], sampled[name] = unique, unique[indices]
        reports[name] = CloudReport(len(points), len(points) - len(unique), count, len(unique) < count)
    init = np.eye(4) if options.init is None else options.init
    source_sampled = apply_transform(sampled["source"], *from_matrix(init))
    normalisation = Normalisation(source_sampled, sampled["target"])
    return _Prepared(
        source=clouds["source"],
        target=clouds["target"],
        source_network=normalisation.source(source_sampled).astype(np.float32),
        target_network=normalisation.target(sampled["target"]).astype(np.float32),
        normalisation=normalisation,
        init=init,
        points=CloudReports(**reports),
        seconds=time.perf_counter() - started,
    )


def _finish(prepared: _Prepared, prediction: Prediction, options: RegistrationOptions) -> RegistrationResult:
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
    if options.refine is not None:
        max_distance = options.refine.max_distance or DEFAULT_DISTANCE_NORMALISED * to_user
        network_transform = to_matrix(rotation, translation)
        rotation, translation, iterations = icp_refine(
            prepared.source,
            prepared.target,
            rotation,
            translation,
            max_distance,
            options.refine.max_iterations,
            max_points=ICP_MAX_POINTS,
            max_seconds=ICP_MAX_SECONDS,
        )
        rotation = nearest_rotation(rotation)
        refinement = RefineReport(max_distance, iterations, network_transform)
    threshold = options.fitness_threshold or DEFAULT_DISTANCE_NORMALISED * to_user
    fitness, inlier_rmse = fitness_and_rmse(
        apply_transform(prepared.source, rotation, translation), prepared.target, threshold
    )
    return RegistrationResult(
        rotation=rotation,
        translation=translation,
        fitness=fitness,
        inlier_rmse=inlier_rmse,
        fitness_threshold=threshold,
        points=prepared.points,
        refinement=refinement,
        timings_ms={
            "queue_ms": prediction.queue_ms,
            "inference_ms": prediction.inference_ms,
            "preprocess_ms": prepared.seconds * 1000.0,
            "postprocess_ms": (time.perf_counter() - started) * 1000.0,
            "batch_size": prediction.batch_size,
        },
    )


async def register_clouds(
    source: np.ndarray,
    target: np.ndarray,
    options: RegistrationOptions,
    settings: Settings,
    predict: Predict,
    run_blocking: RunBlocking = asyncio.to_thread,
) -> RegistrationResult:
    """Register `source` onto `target` (both N x 3 in user units, already through `as_points`).

    `options.network_points` must be set (`resolve_options`). `predict` receives the two
    normalised float32 clouds [network_points, 3] and returns the transform between them (in
    production: the batcher). The CPU-heavy steps run through `run_blocking` (a worker thread by
    default) so that the event loop keeps serving. Raises InvalidInput for clouds that cannot be
    registered.
    """
    prepared = await run_blocking(_prepare, source, target, options, settings)
    prediction = await predict(prepared.source_network, prepared.target_network)
    return await run_blocking(_finish, prepared, prediction, options)


# ---------------------------------------------------------------- a request's pairs


def resolve_options(options: RegistrationOptions, service: ServiceState) -> RegistrationOptions:
    """The options with the network's point count filled in, checked against the service and model."""
    limit, fewest = service.settings.max_network_points, service.model.min_network_points
    count = options.network_points
    if count is not None and count > limit:
        raise InvalidInput("network_points", f"is {count}, more than this service's limit of {limit}")
    if count is not None and count < fewest:
        raise InvalidInput("network_points", f"is {count}; this model needs at least {fewest} points per cloud")
    return options.model_copy(update={"network_points": count or service.model.network_points})


async def register_pairs(
    service: ServiceState, request: Request, pairs: list[tuple[np.ndarray, np.ndarray]], options: RegistrationOptions
) -> list[RegistrationResult]:
    """Run pairs through the registration pipeline and the shared batcher, concurrently.

    With several pairs, errors name the pair (`source[1]`). All pairs are dropped from the
    queue if the client disconnects while they wait.
    """
    assert service.batcher is not None
    options = resolve_options(options, service)
    room = service.batcher.max_queue_size
    if len(pairs) > room:  # could never be queued at once, however long the client waited
        raise InvalidInput(
            "source", f"holds {len(pairs)} pairs, more than this service queues at once; send at most {room}"
        )
    # No wait limit of the batcher's own: the request's deadline bounds the whole request, and
    # cancelling it drops the pair from the queue.
    predict = service.batcher.submit

    async def one(index: int, source: np.ndarray, target: np.ndarray) -> RegistrationResult:
        try:
            return await register_clouds(source, target, options, service.settings, predict)
        except InvalidInput as error:
            if len(pairs) == 1:
                raise
            raise InvalidInput(f"{error.field}[{index}]", error.problem) from None

    async def all_pairs() -> list[RegistrationResult]:
        tasks = [asyncio.ensure_future(one(index, *pair)) for index, pair in enumerate(pairs)]
        try:
            return list(await asyncio.gather(*tasks))
        except BaseException:
            for task in tasks:
                task.cancel()
            raise

    return await cancel_on_disconnect(request, all_pairs())


@asynccontextmanager
async def request_deadline(settings: Settings) -> AsyncIterator[None]:
    """Bounds a whole request (reading, parsing, preprocessing, queue, inference) by the timeout.

    Raises RequestTimeoutError (504). Work already handed to a thread (parsing a large file,
    sampling) runs to its end, but the client gets its answer on time and the pair leaves the
    batcher's queue.
    """
    timeout = settings.request_timeout_s
    try:
        async with asyncio.timeout(timeout):
            yield
    except TimeoutError:
        raise RequestTimeoutError(
            f"no answer within the request timeout of {timeout:g} s; retry later or send fewer points"
        ) from None


async def _disconnected(request: Request) -> None:
    """Returns when the client closes the connection (the body must have been read already)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


async def cancel_on_disconnect(request: Request, work: Awaitable[T]) -> T:
    """Await `work`, cancelling it (and raising ClientDisconnected) if the client goes away first."""
    work_task = asyncio.ensure_future(work)
    watcher = asyncio.ensure_future(_disconnected(request))
    try:
        done, _ = await asyncio.wait({work_task, watcher}, return_when=asyncio.FIRST_COMPLETED)
    except asyncio.CancelledError:  # the request's deadline, or the server stopping
        work_task.cancel()
        watcher.cancel()
        await asyncio.wait({work_task})  # its pair leaves the batcher's queue before the answer goes out
        raise
    watcher.cancel()
    if work_task in done:
        return work_task.result()
    work_task.cancel()
    await asyncio.wait({work_task})  # let it unwind: its pair leaves the batcher's queue
    raise ClientDisconnected("the client disconnected before its registration finished")
