"""What the routes share: settings, the engine and batcher, metrics, and the registration entry point."""

import asyncio
import time
from collections.abc import AsyncIterator, Awaitable
from contextlib import asynccontextmanager
from typing import TypeVar

import numpy as np
from starlette.requests import Request

from service.batcher import MicroBatcher, RequestTimeoutError
from service.engine import Engine, ModelInfo
from service.metrics import LatencyWindow, Metrics
from service.registration import (
    InvalidInput,
    RefineParams,
    RegistrationParams,
    RegistrationResult,
    register_clouds,
)
from service.schemas import ModelDescription, RegistrationOptions
from service.settings import Settings

T = TypeVar("T")


class ClientDisconnected(Exception):
    """The client went away before its answer was ready."""


class ServiceState:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.metrics = Metrics(settings.max_batch_size)
        self.latency = LatencyWindow(settings.latency_window)
        self.started_at = time.monotonic()
        self.engine: Engine | None = None
        self.batcher: MicroBatcher | None = None
        self.ready = asyncio.Event()
        self.warmup_error: str | None = None
        self.accepting = True  # False once shutdown has begun
        self.in_flight = 0  # registration requests admitted and not yet answered (see dependencies.admit)
        self.large_json_parse = asyncio.Lock()  # see uploads.parse_json

    @property
    def model(self) -> ModelInfo:
        assert self.engine is not None, "the engine is loaded in the app's lifespan"
        return self.engine.info

    def model_description(self) -> ModelDescription:
        info = self.model
        return ModelDescription(
            name=info.name,
            version=info.version,
            weights_sha256=info.weights_sha256,
            file_sha256=info.file_sha256,
            preset=info.preset,
            native_num_points=info.native_num_points,
        )

    @asynccontextmanager
    async def deadline(self) -> AsyncIterator[None]:
        """Bounds a whole request (reading, parsing, preprocessing, queue, inference) by the timeout.

        Raises RequestTimeoutError (504). Work already handed to a thread (parsing a large file,
        sampling) runs to its end, but the client gets its answer on time and the pair leaves the
        batcher's queue.
        """
        timeout = self.settings.request_timeout_s
        try:
            async with asyncio.timeout(timeout):
                yield
        except TimeoutError:
            raise RequestTimeoutError(
                f"no answer within the request timeout of {timeout:g} s; retry later or send fewer points"
            ) from None

    def params(self, options: RegistrationOptions) -> RegistrationParams:
        limit = self.settings.max_network_points
        if options.max_points is not None and options.max_points > limit:
            raise InvalidInput("max_points", f"is {options.max_points}, more than this service's limit of {limit}")
        fewest = self.model.min_num_points
        if options.max_points is not None and options.max_points < fewest:
            raise InvalidInput(
                "max_points", f"is {options.max_points}; this model needs at least {fewest} points per cloud"
            )
        refine = options.refine
        return RegistrationParams(
            num_points=options.max_points or self.model.native_num_points,
            sampling=options.sampling,
            seed=options.seed,
            init=options.init,
            refine=None if refine is None else RefineParams(refine.max_distance, refine.max_iterations),
            fitness_threshold=options.fitness_threshold,
            min_points=self.settings.min_points,
            max_cloud_points=self.settings.max_cloud_points,
            fps_max_input_points=self.settings.fps_max_input_points,
        )

    async def register(
        self, request: Request, pairs: list[tuple[np.ndarray, np.ndarray]], options: RegistrationOptions
    ) -> list[RegistrationResult]:
        """Run pairs through the registration pipeline and the shared batcher, concurrently.

        With several pairs, errors name the pair (`source[1]`). All pairs are dropped from the
        queue if the client disconnects while they wait.
        """
        assert self.batcher is not None
        params = self.params(options)
        room = self.batcher.max_queue_size
        if len(pairs) > room:  # could never be queued at once, however long the client waited
            raise InvalidInput(
                "source", f"holds {len(pairs)} pairs, more than this service queues at once; send at most {room}"
            )
        # No wait limit of the batcher's own: the request's deadline (see `deadline`) bounds the
        # whole request, and cancelling it drops the pair from the queue.
        predict = self.batcher.submit

        async def one(index: int, source: np.ndarray, target: np.ndarray) -> RegistrationResult:
            try:
                return await register_clouds(source, target, params, predict)
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
