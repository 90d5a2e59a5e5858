"""`python -m service` / `ifnet-serve`: run the registration service with uvicorn.

Every setting comes from `IFNET_*` environment variables (see service.settings); the flags
below override them.
"""

import argparse
import contextlib
import logging
import math
import os
import shutil
import socket
import sys
import tempfile

from pydantic import ValidationError

from service.engine import ModelLoadError, load_models
from service.settings import Settings


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ifnet-serve",
        description="Serve IFNet point-cloud registration over HTTP. Other settings: IFNET_* environment variables.",
    )
    parser.add_argument("--host", help="interface to listen on (default 127.0.0.1, env IFNET_HOST)")
    parser.add_argument("--port", type=int, help="TCP port (default 8000, env IFNET_PORT)")
    parser.add_argument(
        "--model-repository",
        help="folder of the ONNX models, each served under its file name without .onnx "
        "(default: the shipped service/models, env IFNET_MODEL_REPOSITORY)",
    )
    parser.add_argument("--model-path", help="one ONNX model to serve alone instead (env IFNET_MODEL_PATH)")
    parser.add_argument(
        "--workers", type=int, help="processes serving the port (default: the usable CPUs, env IFNET_WORKERS)"
    )
    parser.add_argument(
        "--threads", type=int, help="ONNX Runtime threads of a worker's lone model call (default: the usable CPUs)"
    )
    parser.add_argument(
        "--log-level",
        choices=["critical", "error", "warning", "info", "debug"],
        help="default info, env IFNET_LOG_LEVEL",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    overrides = {name: value for name, value in vars(args).items() if value is not None}
    try:
        settings = Settings(**overrides)
    except ValidationError as error:
        print(f"ifnet-serve: invalid settings:\n{error}", file=sys.stderr)
        return 2
    settings.configure_logging()
    if settings.workers > 1:
        return serve_workers(settings, overrides)
    # Load the models before binding the port: a bad model file fails at once with its reason.
    try:
        engines = load_models(settings)
    except ModelLoadError as error:
        print(f"ifnet-serve: cannot start: {error}", file=sys.stderr)
        return 1

    import uvicorn

    from service.app import create_app
    from service.protocol import ServiceServer, service_protocol

    app = create_app(settings, engines=engines)
    config = uvicorn.Config(app, http=service_protocol(settings), **server_options(settings))
    sockets = listen(settings)
    if sockets is None:
        return 1
    server = ServiceServer(config)
    with contextlib.suppress(KeyboardInterrupt):  # uvicorn raises the signal it caught again once it has stopped
        server.run(sockets=sockets)
    return 0 if server.started else 1


def listen(settings: Settings) -> list[socket.socket] | None:
    """A socket per worker on the service's port (service.supervisor), or None having said why not."""
    from service.supervisor import listening_sockets

    try:
        sockets = listening_sockets(settings.host, settings.port, settings.workers)
    except OSError as error:
        print(
            f"ifnet-serve: cannot start: cannot listen on {settings.host}:{settings.port} ({error.strerror}): "
            "stop what holds that port or choose another (--port, IFNET_PORT)",
            file=sys.stderr,
        )
        return None
    host, port = sockets[0].getsockname()[:2]
    url = f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"
    logging.getLogger("service").info("listening on %s with %d worker(s) (Ctrl+C stops)", url, len(sockets))
    return sockets


def server_options(settings: Settings) -> dict:
    """uvicorn's options, the same for one process and for several."""
    return {
        "host": settings.host,
        "port": settings.port,
        "log_level": settings.log_level,
        "timeout_graceful_shutdown": math.ceil(settings.shutdown_timeout_s),  # uvicorn takes whole seconds
        # The head deadline bounds idle connections; uvicorn's 5 s raced clients' own 5 s keep-alive.
        "timeout_keep_alive": math.ceil(settings.request_head_timeout_s) + 1,
        "h11_max_incomplete_event_size": settings.max_head_bytes,  # the same bound for a head over several reads
    }


def serve_workers(settings: Settings, overrides: dict) -> int:
    """`settings.workers` processes on one port, each on a socket of its own, under uvicorn's
    supervisor (service.supervisor), which forwards SIGTERM to each (each drains its requests) and
    stops them all if one fails to start (a bad model file: the worker prints which and why). Exits 1 then."""
    import uvicorn
    from uvicorn.config import STARTUP_FAILURE

    from service.metrics import WORKERS_FOLDER_VARIABLE
    from service.supervisor import Supervisor

    sockets = listen(settings)
    if sockets is None:
        return 1
    # The workers are fresh interpreters: they read the flags from the environment, as the settings.
    os.environ.update({f"IFNET_{name.upper()}": str(value) for name, value in overrides.items()})
    metrics = tempfile.mkdtemp(prefix="ifnet-metrics-")
    os.environ[WORKERS_FOLDER_VARIABLE] = metrics
    try:
        config = uvicorn.Config(
            "service.workers:app",
            factory=True,
            http="service.workers:protocol",
            workers=settings.workers,
            **server_options(settings),
        )
        supervisor = Supervisor(config, sockets)
        supervisor.run()
    finally:
        shutil.rmtree(metrics, ignore_errors=True)
    if any(process.exitcode == STARTUP_FAILURE for process in supervisor.processes):
        return 1  # the worker has said why
    return 0


if __name__ == "__main__":
    sys.exit(main())
