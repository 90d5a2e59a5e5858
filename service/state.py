"""What the routes share: settings, the engine and batcher, metrics and the service's life cycle."""

import asyncio
import time

from service.batcher import MicroBatcher
from service.engine import Engine, ModelInfo
from service.metrics import LatencyWindow, Metrics
from service.schemas import ModelDescription
from service.settings import Settings


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
        return ModelDescription.model_validate(self.model, from_attributes=True)
