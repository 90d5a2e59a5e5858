"""Every setting of the service, read from `IFNET_*` environment variables (or passed explicitly)."""

import logging
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.cpus import available_cpus

MODEL_REPOSITORY = Path(__file__).resolve().parent / "models"


class Settings(BaseSettings):
    """Service configuration. Each field `name` is also read from the variable `IFNET_NAME`."""

    model_config = SettingsConfigDict(env_prefix="IFNET_", extra="ignore", protected_namespaces=())

    host: str = Field("127.0.0.1", description="Interface to listen on.")
    port: int = Field(8000, ge=0, le=65535, description="TCP port to listen on.")
    model_repository: Path = Field(
        MODEL_REPOSITORY,
        description="Folder of the served models: every `*.onnx` file in it (an IFNet export), named by its file "
        "name without `.onnx`; requests that name no model use `object`.",
    )
    model_path: Path | None = Field(
        None, description="One ONNX model file to serve alone instead of the repository's, named as there."
    )
    # Most of a pair's work (refinement, sampling, parsing; feature matching too, but in a child process)
    # holds Python's interpreter lock, so one process keeps about one CPU busy however many requests it has.
    workers: int | None = Field(
        None,
        ge=1,
        le=64,
        description="Processes serving the port, each with its own copy of the models and its own `max_in_flight`, "
        "`max_queue_size`, /health and /ready (/metrics adds them all up); default: the usable CPUs.",
    )
    threads: int | None = Field(
        None,
        ge=1,
        description="ONNX Runtime threads of a worker's model call that runs alone, with no other call or request "
        "in its worker (calls beside others, of any model, share them out); default: the usable CPUs.",
    )
    # One call per CPU in the whole service, no batching: what served most pairs/s when measured.
    model_calls: int | None = Field(
        None,
        ge=1,
        le=16,
        description="Model calls a worker runs at once, whatever their models (at most one per thread): one that "
        "runs alone gets all `threads`, any other `threads` / (model_calls x workers); default: `threads` shared "
        "out among the workers (2 with one worker on 2 CPUs, 1 with two).",
    )
    max_batch_size: int = Field(1, ge=1, le=64, description="Most requests run in one model call.")
    max_batch_delay_ms: float = Field(
        0.0, ge=0.0, le=1000.0, description="How long a batch waits to fill up; 0 takes whatever is waiting."
    )
    # Keeps the slowest admitted request inside the default timeout and the bodies' memory bounded.
    max_in_flight: int = Field(
        16,
        ge=1,
        description="Registration requests admitted at once (reading, parsing, queued or running); more get 429 "
        "before their body is read, which bounds the memory and CPU that request bodies can take.",
    )
    max_queue_size: int = Field(64, ge=1, description="Pairs that may wait for one model; more get 429.")
    request_timeout_s: float = Field(
        30.0,
        gt=0.0,
        description="Longest time for a whole request (body, parsing, sampling, queue, inference); longer gets 504.",
    )
    request_head_timeout_s: float = Field(
        10.0,
        gt=0.0,
        description="Longest time a connection may take to send a request's headers, from opening or from its "
        "previous answer; then it is closed (408 if part of a head arrived). Bounds idle and slowloris connections.",
    )
    max_head_bytes: int = Field(
        16 * 1024,
        ge=1024,
        le=1024 * 1024,
        description="Largest request head (request line and headers); larger gets 431.",
    )
    max_body_bytes: int = Field(64 * 1024 * 1024, ge=1024, description="Largest request body; larger gets 413.")
    min_points: int = Field(32, ge=8, description="Fewest distinct points a cloud must have.")
    max_cloud_points: int = Field(500_000, ge=1, description="Most points one cloud may have.")
    max_network_points: int = Field(2048, ge=8, description="Largest per-request `network_points`.")
    fps_max_input_points: int = Field(
        8_192,
        ge=1024,
        description="Farthest-point sampling of larger clouds starts from a seeded random subset of this size.",
    )
    default_method: Literal["auto", "ifnet", "global"] = Field(
        "auto",
        description="The registration method of requests that do not name one: `ifnet` bounds every request to one "
        "model call, `auto` adds the global search where the network's answer fails its check.",
    )
    isolate_feature_matching: bool = Field(
        True,
        description="Run feature matching (KISS-Matcher, native code) in a child process of each worker: a crash "
        "there costs the pairs in it their feature guess (they are answered without it), not the worker and every "
        "request in flight on it, and the worker serves on while it runs.",
    )
    feature_matching_max_mb: float = Field(
        256.0,
        gt=0.0,
        description="Feature matching's child process is replaced by a new one once its resident memory passes this "
        "many MB: KISS-Matcher never frees part of what each call allocates (about 0.5 MB per pair of real scans). "
        "With isolate_feature_matching off, that memory accumulates in the worker.",
    )
    warmup: bool = Field(True, description="Run each model once per batch size before reporting ready.")
    shutdown_timeout_s: float = Field(30.0, gt=0.0, description="Grace period for in-flight requests on SIGTERM.")
    log_level: Literal["critical", "error", "warning", "info", "debug"] = "info"
    api_key: SecretStr | None = Field(
        None, description="If set, /register and v2 inference need it in `X-API-Key` or `Authorization: Bearer`."
    )
    api_key_scope: Literal["inference", "all"] = Field(
        "inference",
        description="With an API key: `inference` guards /register and v2 inference only; `all` guards every route "
        "but the probes (/health, /ready, /v2/health/*, /v2/models/{name}/ready): /metrics, /docs, /openapi.json, "
        "/v2/models/{name} too.",
    )
    latency_window: int = Field(1000, ge=10, description="Recent /register requests the /health percentiles cover.")

    @model_validator(mode="after")
    def _one_call_per_thread(self) -> "Settings":
        """`workers` and `threads` default to the usable CPUs and `model_calls` to a worker's share of
        the threads, and `model_calls` is at most one per thread: calls beyond that would only take
        turns on the CPUs."""
        if self.workers is None:
            self.workers = available_cpus()
        if self.threads is None:
            self.threads = available_cpus()
        if self.model_calls is None:
            self.model_calls = max(1, self.threads // self.workers)
        self.model_calls = min(self.model_calls, self.threads)
        return self

    def configure_logging(self) -> None:
        """The service's own log lines (models loaded, warm-up, shutdown) beside uvicorn's."""
        logging.basicConfig(level=self.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    @field_validator("api_key", mode="before")
    @classmethod
    def _blank_key_means_none(cls, value: object) -> object:
        """An empty IFNET_API_KEY (e.g. an unset optional secret) disables the check rather than
        requiring an empty key."""
        return None if isinstance(value, str) and not value.strip() else value
