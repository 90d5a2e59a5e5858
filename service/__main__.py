"""`python -m service` / `ifnet-serve`: run the registration service with uvicorn.

Every setting comes from `IFNET_*` environment variables (see service.settings); the flags
below override them.
"""

import argparse
import logging
import math
import sys

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
    parser.add_argument("--threads", type=int, help="ONNX Runtime intra-op threads (default: the usable CPUs)")
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
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # Load the models before binding the port: a bad model file fails at once with its reason.
    try:
        engines = load_models(settings)
    except ModelLoadError as error:
        print(f"ifnet-serve: cannot start: {error}", file=sys.stderr)
        return 1

    import uvicorn

    from service.app import create_app
    from service.protocol import service_protocol

    uvicorn.run(
        create_app(settings, engines=engines),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=math.ceil(settings.shutdown_timeout_s),  # uvicorn takes whole seconds
        http=service_protocol(settings),
        h11_max_incomplete_event_size=settings.max_head_bytes,  # the same bound for a head over several reads
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
