"""What the routes share: settings, the models (each an engine and its batcher), metrics and the
service's life cycle."""

import asyncio
import time
from dataclasses import dataclass

from service.batcher import MicroBatcher
from service.engine import Engine, ModelInfo, RunningCalls
from service.features import IsolatedFeatureMatch
from service.metrics import LatencyWindow, Metrics
from service.schemas import DraftDescription, ModelDescription
from service.settings import Settings
from service.validation import InvalidInput


@dataclass(frozen=True)
class ServedModel:
    """One model of the repository: its engine and the batcher in front of it, and its draft's."""

    engine: Engine
    batcher: MicroBatcher
    draft: MicroBatcher | None  # in front of engine.draft

    @property
    def info(self) -> ModelInfo:
        return self.engine.info

    @property
    def batchers(self) -> list[MicroBatcher]:
        return [self.batcher] if self.draft is None else [self.batcher, self.draft]

    @property
    def queue_depth(self) -> int:
        return sum(batcher.queue_depth for batcher in self.batchers)

    def description(self) -> ModelDescription:
        description = ModelDescription.model_validate(self.info)
        if self.draft is None:
            return description
        info = self.draft.engine.info
        config = info.config or {}
        blocks = config["time_steps"] * config["n_iters"] if {"time_steps", "n_iters"} <= config.keys() else None
        draft = DraftDescription(version=info.version, network_points=info.network_points, blocks=blocks)
        return description.model_copy(update={"draft": draft})


class ServiceState:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.metrics = Metrics(settings.max_batch_size)
        self.latency = LatencyWindow(settings.latency_window)
        self.started_at = time.monotonic()
        # By name, in the order `auto` asks them (the default first); empty until the app's lifespan loads them.
        self.models: dict[str, ServedModel] = {}
        self.ready = asyncio.Event()  # every model loaded and warmed up: they are served all or none
        self.warmup_error: str | None = None
        self.accepting = True  # False once shutdown has begun
        self.running = RunningCalls()  # the engines' own, once they are served
        self.large_json_parse = asyncio.Lock()  # see uploads.parse_json
        self.feature_match: IsolatedFeatureMatch | None = None  # None: feature matching in the worker itself
        if settings.isolate_feature_matching:
            failures = self.metrics.feature_matching_failures
            self.feature_match = IsolatedFeatureMatch(
                on_failure=lambda reason: failures.labels(reason).inc(),
                max_mb=settings.feature_matching_max_mb,
                on_replaced=self.metrics.feature_matching_replaced.inc,
            )

    @property
    def in_flight(self) -> int:
        """Registration requests admitted and not yet answered (see dependencies.admit); counted
        with the model calls, whose threads depend on it."""
        return self.running.requests

    @in_flight.setter
    def in_flight(self, count: int) -> None:
        self.running.requests = count

    def serve(self, engines: list[Engine]) -> None:
        """A batcher for each engine and its draft, in the engines' order (their model calls share
        `model_calls` slots), and its metrics."""
        settings = self.settings
        if isinstance(running := getattr(engines[0], "running", None), RunningCalls):  # stand-in engines have none
            self.running = running
        slots = asyncio.Semaphore(settings.model_calls)

        def batcher(engine: Engine) -> MicroBatcher:
            self.metrics.add_model(engine.info.name, engine.info.version, engine.info.network_points)
            return MicroBatcher(
                engine,
                max_batch_size=settings.max_batch_size,
                max_queue_size=settings.max_queue_size,
                max_batch_delay_ms=settings.max_batch_delay_ms,
                model_calls=settings.model_calls,
                slots=slots,
                metrics=self.metrics,
            )

        for engine in engines:
            draft = getattr(engine, "draft", None)  # OnnxEngine's; stand-in engines have none
            draft = None if draft is None else batcher(draft)
            self.models[engine.info.name] = ServedModel(engine, batcher(engine), draft)

    def model(self, name: str | None) -> ServedModel:
        """The model a request names, or the default (the first) when it names none."""
        if name is None:
            return next(iter(self.models.values()))
        if name not in self.models:
            raise InvalidInput("model", f"is {name!r}, not a model of this service; choose one of {list(self.models)}")
        return self.models[name]
