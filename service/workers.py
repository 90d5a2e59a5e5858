"""What each worker process serves when `workers` > 1: uvicorn's supervisor starts the workers,
each imports this module, reads the IFNET_* settings from the environment the supervisor passed
on (its command-line flags included) and loads its own copy of the models."""

import sys

from uvicorn.config import STARTUP_FAILURE

from service.app import create_app
from service.engine import ModelLoadError, load_models
from service.protocol import service_protocol
from service.settings import Settings

settings = Settings()
settings.configure_logging()
protocol = service_protocol(settings)


def app():
    """uvicorn's app factory (`service.workers:app`). A model that fails to load ends this worker as
    a failed start, upon which the supervisor stops the others and exits."""
    try:
        engines = load_models(settings)
    except ModelLoadError as error:
        print(f"ifnet-serve: cannot start: {error}", file=sys.stderr)
        sys.exit(STARTUP_FAILURE)
    return create_app(settings, engines=engines)
