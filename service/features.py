"""Feature matching (model.geometry.feature_match: KISS-Matcher, native code) in a child process of
the worker's own.

A crash in native code ends the process it runs in. In the worker, that lost every request in flight
there (uvicorn starts another worker; their clients see the connection close without an answer). In
the child it costs one request its feature guess: the matcher answers as where it finds nothing (the
identity, which the check then fails), the request goes on to the networks and the rotated starts,
and the next request gets a new child. So does a child stuck in native code, which is killed. The
matcher also holds the interpreter lock while it runs (70-150 ms on a real scan's pair): in the
child, the worker's event loop and other threads go on meanwhile. And it keeps part of what each
call allocates (about 0.5 MB per real scan's pair, never freed): a child grown past its memory bound
is replaced, between calls.
"""

import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np

from model.geometry import FEATURE_VOXEL_SPACINGS, feature_match

logger = logging.getLogger(__name__)

FeatureMatch = Callable[..., tuple[np.ndarray, np.ndarray]]  # feature_match's signature
FAILURES = ("crash", "timeout")  # the reasons a call answers without the matcher (on_failure's argument)
PARENT_POLL_S = 1.0  # how often the child looks whether its worker still lives
MAX_SECONDS = 10.0  # a call that takes longer is stuck (0.15 s at most on the benchmarks' real scans)


def resident_mb(pid: int) -> float:
    """The process's resident memory in MB, from /proc; 0 where that cannot be read."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0
    return next((int(line.split()[1]) / 1024 for line in status.splitlines() if line.startswith("VmRSS:")), 0.0)


def _serve(connection: Connection, parent: int) -> None:
    """The child: answers each (function, *arguments) it receives with ("ok", result) or ("error",
    exception), until the worker closes its end or is gone. A worker killed outright (SIGKILL, the
    OOM killer) never closes it, so the child also looks for its parent every PARENT_POLL_S."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    # The matcher's OpenMP threads sleep once its work is done: spinning, they took the CPUs from the
    # worker's refinement that follows (the isolated requests were 15 % slower on ModelNet pairs).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import kiss_matcher  # noqa: F401  (loaded before the first request needs it)

    connection.send(("ok", None))
    while True:
        try:
            function, *arguments = connection.recv()
        except EOFError:
            return
        try:
            answer = ("ok", function(*arguments))
        except Exception as error:
            answer = ("error", error)
        connection.send(answer)


class IsolatedFeatureMatch:
    """feature_match(source, target, spacing, spacings), run in one child process, one call at a time:
    spawned (not forked: the worker runs ONNX Runtime's threads) by `start` or the first call, and
    again by the first call after a failure: a crash, or no answer within MAX_SECONDS (the child is
    then killed). Either way the call answers as feature matching does where it finds nothing, and
    `on_failure` gets the reason, one of FAILURES (the service counts them). The calling thread talks to the
    child itself, with no thread between them: each hand-over between threads waits for the
    interpreter lock. A child whose resident memory passes `max_mb` after a call is replaced by a
    new one on a thread of its own, off that call's time, and `on_replaced` is called."""

    def __init__(
        self,
        match: FeatureMatch = feature_match,
        on_failure: Callable[[str], None] = lambda reason: None,
        max_mb: float | None = None,
        on_replaced: Callable[[], None] = lambda: None,
    ):
        self.match, self.on_failure = match, on_failure
        self.max_mb, self.on_replaced = max_mb, on_replaced
        self._lock = threading.Lock()  # calls come from the requests' worker threads
        self._child: multiprocessing.process.BaseProcess | None = None
        self._connection: Connection | None = None
        self._closed = False  # no child is spawned to replace one once closed

    def _running(self) -> Connection:
        """The child's end of the pipe, the child spawned first where none runs. Holds the lock."""
        if self._connection is None:
            context = multiprocessing.get_context("spawn")
            ours, theirs = context.Pipe()
            self._child = context.Process(
                target=_serve, args=(theirs, os.getpid()), name="feature-matching", daemon=True
            )
            self._child.start()
            theirs.close()
            self._connection = ours
            self._connection.recv()  # imported and ready
        return self._connection

    def start(self) -> None:
        """The child spawned and the matcher imported in it now, rather than on a request's time."""
        with self._lock:
            self._running()

    def __call__(
        self, source: np.ndarray, target: np.ndarray, spacing: float, spacings: float = FEATURE_VOXEL_SPACINGS
    ) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            failure = grown = None
            try:
                connection = self._running()
                connection.send((self.match, source, target, spacing, spacings))
                if connection.poll(MAX_SECONDS):
                    status, answer = connection.recv()
                else:
                    failure = "timeout"
            except (EOFError, OSError):  # the child died on these clouds
                failure = "crash"
            if failure is not None:
                self._stop(kill=True)
            elif self.max_mb is not None and (size := resident_mb(self._child.pid)) > self.max_mb:
                grown = (self._child, size)
        if grown is not None:
            threading.Thread(target=self._replace, args=grown, name="feature-matching-replace", daemon=True).start()
        if failure is not None:
            self.on_failure(failure)
            logger.error(
                "feature matching %s on clouds of %d and %d points; answering without its guess",
                "crashed" if failure == "crash" else f"gave no answer within {MAX_SECONDS:g} s",
                len(source),
                len(target),
            )
            return np.eye(3), np.zeros(3)
        if status == "error":
            raise answer
        return answer

    def _replace(self, grown: multiprocessing.process.BaseProcess, size: float) -> None:
        """A new child in place of `grown` (found holding `size` MB), unless it was replaced or closed meanwhile."""
        with self._lock:
            if self._child is not grown or self._closed:
                return
            self._stop()
            try:
                self._running()
            except Exception:  # the next call spawns one, or fails as it would without this
                logger.exception("feature matching's new process failed to start")
                return
        self.on_replaced()
        logger.info("feature matching's process replaced: it held %.0f MB, more than %.0f", size, self.max_mb)

    def _stop(self, kill: bool = False) -> None:
        """Close the pipe, upon which the child ends (killed at once with `kill`: it may be stuck), and
        reap it. Holds the lock."""
        if self._connection is not None:
            self._connection.close()
        if self._child is not None:
            if kill:
                self._child.kill()
            self._child.join(timeout=5)
            if self._child.is_alive():
                self._child.kill()
                self._child.join()
        self._child = self._connection = None

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._stop()
