"""An asyncio micro-batcher in front of the model: requests queue, workers run them in batches.

Each submitted pair gets a future. A worker takes up to `max_batch_size` waiting pairs (after
an optional delay to let more arrive), runs one model call per input shape on a thread of its
own so that the event loop stays free, and resolves the futures. `model_calls` workers
(default 1) take batches side by side, each with its own thread; the batchers of several models
share `slots`, so that no more than that many calls run at once in all. A pair whose caller gave
up (timeout, client disconnect) has a cancelled future: the worker skips it, or drops its result.
"""

import asyncio
import contextlib
import logging
import math
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from service.engine import Engine, warm_up_engine
from service.metrics import Metrics

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prediction:
    """The model's transform between the normalised clouds, and what it cost."""

    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3], normalised units
    queue_ms: float = 0.0
    inference_ms: float = 0.0
    batch_size: int = 1


class QueueFullError(Exception):
    """The queue holds max_queue_size pairs already: the client should retry after `retry_after_s`."""

    def __init__(self, retry_after_s: int):
        super().__init__(f"the service is busy: the inference queue is full; retry after {retry_after_s} s")
        self.retry_after_s = retry_after_s


class RequestTimeoutError(Exception):
    """A pair waited longer than its timeout for the model."""


class ShuttingDownError(Exception):
    """The batcher no longer accepts work: the service is stopping."""


class InferenceError(RuntimeError):
    """The model call failed (a server-side fault, not the client's input)."""


@dataclass(eq=False)
class _Pending:
    source: np.ndarray
    target: np.ndarray
    future: asyncio.Future
    beside: bool = False  # its caller does CPU work of its own meanwhile (Engine.run)
    began: asyncio.Event = field(default_factory=asyncio.Event)  # set when a thread takes its call up
    enqueued_at: float = field(default_factory=time.perf_counter)
    taken: bool = False


class MicroBatcher:
    def __init__(
        self,
        engine: Engine,
        *,
        max_batch_size: int,
        max_queue_size: int,
        max_batch_delay_ms: float = 0.0,
        model_calls: int = 1,
        slots: asyncio.Semaphore | None = None,
        metrics: Metrics | None = None,
    ):
        self.engine = engine
        self.max_batch_size = max_batch_size
        self.max_queue_size = max_queue_size
        self.max_batch_delay_s = max_batch_delay_ms / 1000.0
        self.metrics = metrics
        self._queue: asyncio.Queue[_Pending] = asyncio.Queue()  # bounded by _waiting, see submit
        self._waiting = 0  # queued pairs whose caller still waits
        self._running = 0  # pairs in the model calls under way
        self._idle = asyncio.Event()
        self._idle.set()
        self._closing = False
        self.model_calls = model_calls
        self._slots = slots or asyncio.Semaphore(model_calls)  # model calls under way, of this batcher's and others'
        self._workers: list[asyncio.Task] = []
        self._batch_seconds = 1.0  # running estimate of one model call, for Retry-After
        # One thread per worker: ORT parallelises inside a call with the engine's threads.
        self._executor = ThreadPoolExecutor(max_workers=model_calls, thread_name_prefix="ifnet-inference")

    # ------------------------------------------------------------ lifecycle

    async def warm_up(self, network_points: int) -> None:
        """One model call at every batch size the worker may use (1 .. max_batch_size)."""
        started = time.perf_counter()
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(
            self._executor, warm_up_engine, self.engine, range(1, self.max_batch_size + 1), network_points
        )
        logger.info("warm-up of batch sizes 1..%d took %.2f s", self.max_batch_size, time.perf_counter() - started)

    def start(self) -> None:
        if not self._workers:
            loop = asyncio.get_running_loop()
            self._workers = [loop.create_task(self._work(), name=f"ifnet-batcher-{i}") for i in range(self.model_calls)]

    async def close(self, grace_s: float) -> None:
        """Stop accepting pairs, let queued and running ones finish (up to grace_s), then stop."""
        self._closing = True
        try:
            await asyncio.wait_for(self._idle.wait(), grace_s)
        except TimeoutError:
            logger.warning("batcher: %d pairs still waiting after %.1f s; abandoning them", self._waiting, grace_s)
        for worker in self._workers:
            worker.cancel()
        for worker in self._workers:
            with contextlib.suppress(asyncio.CancelledError):
                await worker
        while not self._queue.empty():
            pending = self._queue.get_nowait()
            if not pending.future.done():
                pending.future.set_exception(ShuttingDownError("the service stopped before this request ran"))
        self._executor.shutdown(wait=False, cancel_futures=True)

    # ------------------------------------------------------------ clients

    @property
    def model(self) -> str:
        """The engine's model name: the label of this batcher's metrics."""
        return self.engine.info.name

    @property
    def queue_depth(self) -> int:
        return self._waiting

    @property
    def accepting(self) -> bool:
        return not self._closing

    def retry_after_s(self) -> int:
        """Rough time until the queue has room again: the batches ahead times a recent batch duration."""
        batches_ahead = math.ceil(self._waiting / self.max_batch_size) + 1
        return max(1, math.ceil(batches_ahead * self._batch_seconds / self.model_calls))

    async def submit(self, source: np.ndarray, target: np.ndarray, timeout_s: float | None = None) -> Prediction:
        """Queue one normalised pair ([N, 3], [M, 3] float32) and wait for the model's answer.

        Raises QueueFullError when the queue is full, RequestTimeoutError after timeout_s, and
        ShuttingDownError once close() has begun. Cancelling the caller drops the pair.
        """
        return await self._answer(self._enqueue(source, target, beside=False), timeout_s)

    async def start_beside(self, source: np.ndarray, target: np.ndarray) -> "asyncio.Task[Prediction]":
        """Queue one pair whose caller does CPU work of its own while the model runs, and return once
        a thread has taken its call up (to run on the threads of a call beside others), with the task
        of its answer: work the caller starts before that would hold the call back. Raises as submit
        does; cancelling the task drops the pair."""
        pending = self._enqueue(source, target, beside=True)
        answer = asyncio.ensure_future(self._answer(pending, None))
        began = asyncio.ensure_future(pending.began.wait())
        try:
            await asyncio.wait({answer, began}, return_when=asyncio.FIRST_COMPLETED)  # or it failed first
        except asyncio.CancelledError:
            answer.cancel()
            raise
        finally:
            began.cancel()
        return answer

    def _enqueue(self, source: np.ndarray, target: np.ndarray, beside: bool) -> _Pending:
        if self._closing:
            raise ShuttingDownError("the service is shutting down")
        if self._waiting >= self.max_queue_size:
            self._reject("queue_full")
            raise QueueFullError(self.retry_after_s())
        pending = _Pending(source, target, asyncio.get_running_loop().create_future(), beside)
        pending.future.add_done_callback(lambda _: self._forget(pending))
        self._waiting += 1
        self._idle.clear()
        self._update_depth()
        self._queue.put_nowait(pending)
        return pending

    async def _answer(self, pending: _Pending, timeout_s: float | None) -> Prediction:
        try:
            return await asyncio.wait_for(pending.future, timeout_s)
        except TimeoutError:
            self._reject("timeout")
            raise RequestTimeoutError(
                f"no model result within {timeout_s:g} s (the service is overloaded); retry later"
            ) from None
        except asyncio.CancelledError:
            self._reject("cancelled")
            raise

    # ------------------------------------------------------------ worker

    def _forget(self, pending: _Pending) -> None:
        """Done callback: a pair cancelled while still queued no longer counts as waiting."""
        if not pending.taken:
            pending.taken = True
            self._waiting -= 1
            self._update_depth()
            self._check_idle()

    def _take(self, pending: _Pending, batch: list[_Pending]) -> None:
        if pending.taken:  # cancelled while queued: already forgotten
            return
        pending.taken = True
        self._waiting -= 1
        self._running += 1
        batch.append(pending)

    async def _fill(self, batch: list[_Pending]) -> None:
        """Wait for a first pair, then add whatever else is waiting (after the optional delay)."""
        while not batch:
            self._take(await self._queue.get(), batch)
        if self.max_batch_delay_s > 0:
            deadline = time.perf_counter() + self.max_batch_delay_s
            while len(batch) < self.max_batch_size and (remaining := deadline - time.perf_counter()) > 0:
                try:
                    self._take(await asyncio.wait_for(self._queue.get(), remaining), batch)
                except TimeoutError:
                    break
        while len(batch) < self.max_batch_size and not self._queue.empty():
            self._take(self._queue.get_nowait(), batch)

    async def _work(self) -> None:
        batch: list[_Pending] = []
        try:
            while True:
                batch = []
                await self._fill(batch)
                self._update_depth()
                try:
                    async with self._slots:
                        await self._run(batch)
                except Exception as error:  # a bug here must not stop the worker for everyone else
                    logger.exception("batch of %d failed", len(batch))
                    self._fail(batch, InferenceError(f"inference failed: {error}"))
                self._running -= len(batch)
                self._check_idle()
        except asyncio.CancelledError:
            self._fail(batch, ShuttingDownError("the service stopped before this request finished"))
            raise

    @staticmethod
    def _fail(batch: list[_Pending], error: Exception) -> None:
        for pending in batch:
            if not pending.future.done():
                pending.future.set_exception(error)

    async def _run(self, batch: list[_Pending]) -> None:
        # Pairs stack only when their point counts agree (requests may choose network_points), and a
        # batch runs beside its callers' work if any of them asked.
        groups: dict[tuple, list[_Pending]] = defaultdict(list)
        for pending in batch:
            groups[(pending.source.shape, pending.target.shape)].append(pending)
        loop = asyncio.get_running_loop()
        for items in groups.values():
            items = [pending for pending in items if not pending.future.done()]  # callers may have left
            if not items:
                continue
            started = time.perf_counter()
            source = np.stack([pending.source for pending in items])
            target = np.stack([pending.target for pending in items])
            try:
                began = [pending.began for pending in items if pending.beside]  # no one waits on the others'
                rotation, translation = await loop.run_in_executor(
                    self._executor, self._call, loop, began, source, target, bool(began)
                )
                rotation, translation = np.asarray(rotation), np.asarray(translation)
                if rotation.shape != (len(items), 3, 3) or translation.shape != (len(items), 3):
                    raise InferenceError(
                        f"model returned rotation {rotation.shape} and translation {translation.shape} "
                        f"for a batch of {len(items)}"
                    )
            except Exception as error:
                logger.exception("model call on a batch of %d failed", len(items))
                self._fail(items, InferenceError(f"inference failed: {error}"))
                continue
            seconds = time.perf_counter() - started
            self._batch_seconds = 0.8 * self._batch_seconds + 0.2 * seconds
            if self.metrics is not None:
                self.metrics.batch_size.labels(self.model).observe(len(items))
                self.metrics.inference.labels(self.model).observe(seconds)
            for index, pending in enumerate(items):
                queued = started - pending.enqueued_at
                if self.metrics is not None:
                    self.metrics.queue_wait.labels(self.model).observe(queued)
                if not pending.future.done():
                    pending.future.set_result(
                        Prediction(
                            rotation=rotation[index].astype(np.float64),
                            translation=translation[index].astype(np.float64),
                            queue_ms=queued * 1000.0,
                            inference_ms=seconds * 1000.0,
                            batch_size=len(items),
                        )
                    )

    def _call(
        self,
        loop: asyncio.AbstractEventLoop,
        began: list[asyncio.Event],
        source: np.ndarray,
        target: np.ndarray,
        beside: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The model call, on the executor's thread, which first tells the callers waiting to run
        beside it (start_beside) that it has taken the call up."""
        for event in began:
            loop.call_soon_threadsafe(event.set)
        return self.engine.run(source, target, beside)

    def _check_idle(self) -> None:
        if self._waiting == 0 and self._running == 0:
            self._idle.set()

    def _update_depth(self) -> None:
        if self.metrics is not None:
            self.metrics.queue_depth.labels(self.model).set(self._waiting)

    def _reject(self, reason: str) -> None:
        if self.metrics is not None:
            self.metrics.rejections.labels(self.model, reason).inc()
