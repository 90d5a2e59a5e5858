"""How the service listens: the port's sockets, one per worker, and, when `workers` > 1, uvicorn's
supervisor with each worker on a socket of its own.

On one shared listening socket, whichever worker woke first accepted a whole burst of new
connections and served them alone while the others idled. Here every worker listens on its own
socket, all bound to the port with SO_REUSEPORT, and the kernel deals new connections out among
them by a hash of the client's address and port. The supervisor reaches into uvicorn's
Multiprocess and Process, pinned with the protocol (service.protocol.TESTED_VERSIONS).
"""

import logging
import signal
import socket

from uvicorn.config import STARTUP_FAILURE
from uvicorn.supervisors.multiprocess import Multiprocess, Process

from service.protocol import ServiceServer

logger = logging.getLogger("uvicorn.error")


def listening_sockets(host: str, port: int, count: int) -> list[socket.socket]:
    """`count` sockets bound to `host:port` (port 0: one free port for all), one per worker to
    listen on. The first is bound alone before the rest share the port, so that a port anything
    else holds fails the start (OSError), even where the holder shares it: two services never
    split one port's connections by mistake."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET

    def bound(port: int, shared: bool) -> socket.socket:
        sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)  # asyncio sets TCP_NODELAY only then
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn: no wait for TIME_WAIT
        if shared:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        try:
            sock.bind((host, port))
        except OSError:
            sock.close()
            raise
        sock.set_inheritable(True)  # the workers are spawned processes
        return sock

    alone = bound(port, shared=False)
    if count == 1:
        return [alone]
    port = alone.getsockname()[1]
    alone.close()
    sockets: list[socket.socket] = []
    try:
        for _ in range(count):
            sockets.append(bound(port, shared=True))
    except OSError:
        for sock in sockets:
            sock.close()
        raise
    return sockets


class _Worker(Process):
    """A worker process of uvicorn's supervisor, served by ServiceServer."""

    @property
    def server(self) -> ServiceServer:
        if self._server is None:
            self._server = ServiceServer(config=self.config)
        return self._server


class Supervisor(Multiprocess):
    """uvicorn's supervisor (signals, health pings, drain on SIGTERM, stop on a failed start) with
    worker k always on `sockets[k]`, a replacement included. The number of workers is fixed."""

    def worker(self, slot: int) -> Process:
        process = _Worker(self.config, [self.sockets[slot]])
        process.start()
        return process

    def init_processes(self) -> None:
        self.processes = [self.worker(slot) for slot in range(self.processes_num)]

    def keep_subprocess_alive(self) -> None:
        for slot, process in enumerate(self.processes):
            if self.should_exit.is_set() or process.is_alive(timeout=self.config.timeout_worker_healthcheck):
                continue
            process.kill()  # it may be alive but deaf to the pings
            process.join()
            if process.exitcode == STARTUP_FAILURE:  # a bad model file: every restart would fail alike
                logger.error("Worker [%s] failed to start, stopping the service.", process.pid)
                self.should_exit.set()
                return
            logger.info("Worker [%s] died; starting another on its socket.", process.pid)
            self.processes[slot] = self.worker(slot)

    def handle_signals(self) -> None:
        for number in (signal.SIGHUP, signal.SIGTTIN, signal.SIGTTOU):
            if number in self.signal_queue:  # uvicorn's restarts and resizes would share sockets out anew
                self.signal_queue.remove(number)
                logger.warning("Ignored %s: restart the service to change its workers.", signal.Signals(number).name)
        super().handle_signals()
