"""The service's own routes: /register, /health, /ready and /metrics."""

import time
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from service.dependencies import AdmittedService, Service, require_api_key
from service.registration import register_pairs, request_deadline
from service.schemas import (
    EXAMPLE_SOURCE,
    EXAMPLE_TARGET,
    ErrorResponse,
    HealthResponse,
    LatencySummary,
    ModelHealth,
    ReadyResponse,
    RegisterResponse,
)
from service.uploads import read_register_body

router = APIRouter()

_MULTIPART_SCHEMA = {
    "type": "object",
    "required": ["source", "target"],
    "properties": {
        "source": {"type": "string", "format": "binary", "description": "PLY, PCD or NPY file of the source."},
        "target": {"type": "string", "format": "binary", "description": "PLY, PCD or NPY file of the target."},
        "options": {
            "type": "string",
            "description": "Optional JSON object with the RegistrationOptions fields.",
            "example": '{"refine": true, "seed": 0}',
        },
    },
}
_BINARY = {"type": "string", "format": "binary"}
REGISTER_REQUEST_BODY = {
    "required": True,
    "content": {
        "application/json": {
            "schema": {"$ref": "#/components/schemas/RegisterRequest"},
            "examples": {
                "plain": {"summary": "Two clouds", "value": {"source": EXAMPLE_SOURCE, "target": EXAMPLE_TARGET}},
                "refined": {
                    "summary": "With an initial guess and ICP refinement",
                    "value": {
                        "source": EXAMPLE_SOURCE,
                        "target": EXAMPLE_TARGET,
                        "init": [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                        "refine": {"max_iterations": 50},
                        "seed": 7,
                    },
                },
            },
        },
        "multipart/form-data": {"schema": _MULTIPART_SCHEMA},
        "application/x-npy": {"schema": {**_BINARY, "description": "One float array of shape [2, N, 3]."}},
        "application/x-npz": {"schema": {**_BINARY, "description": "An NPZ archive with `source` and `target`."}},
    },
}

_ERRORS = {
    400: {"model": ErrorResponse, "description": "Body that cannot be parsed at all (e.g. malformed multipart)."},
    401: {"model": ErrorResponse, "description": "Missing or wrong API key (only when one is configured)."},
    413: {"model": ErrorResponse, "description": "Body larger than the configured limit."},
    415: {"model": ErrorResponse, "description": "Content type or file format not accepted."},
    422: {"model": ErrorResponse, "description": "A field is invalid; `detail` names it and the problem."},
    429: {
        "model": ErrorResponse,
        "description": "Too many requests in progress, or the queue is full; retry after `Retry-After` seconds.",
    },
    503: {"model": ErrorResponse, "description": "Models not loaded yet, or shutting down."},
    504: {"model": ErrorResponse, "description": "No model result within the request timeout."},
}


@router.post(
    "/register",
    response_model=RegisterResponse,
    responses=_ERRORS,
    openapi_extra={"requestBody": REGISTER_REQUEST_BODY},
    dependencies=[Depends(require_api_key)],
    summary="Register two point clouds",
    tags=["registration"],
)
async def register(
    request: Request,
    service: AdmittedService,
    options: Annotated[
        str | None,
        Query(
            description="RegistrationOptions as JSON, for raw NPY/NPZ bodies (multipart may use an `options` part).",
            examples=['{"refine": true}'],
        ),
    ] = None,
) -> RegisterResponse:
    """The rigid transform (R, t) with `target ~ source @ R^T + t`, in the clouds' own units.

    Send the clouds as JSON lists of [x, y, z], as multipart file parts `source` and `target`
    (PLY, PCD or NPY each), or as one raw NPY [2, N, 3] / NPZ (`source`, `target`) body. Exact
    duplicate points are removed (and counted in the answer), each cloud is resampled to the
    network's point count, and both are scaled to the radius of the network's training crops before
    the network runs. The `model` option picks the network by name (`GET /v2/models` lists them).
    """
    started = time.perf_counter()
    async with request_deadline(service.settings):
        source, target, parsed = await read_register_body(request, options, service.settings)
        read_ms = (time.perf_counter() - started) * 1000.0
        (result,) = await register_pairs(service, request, [(source, target)], parsed)
    total_ms = (time.perf_counter() - started) * 1000.0
    return RegisterResponse.from_result(result, service.model(result.model).description(), read_ms, total_ms)


@router.get(
    "/health",
    response_model=HealthResponse,
    responses={503: {"model": HealthResponse, "description": "A model's warm-up failed: restart the process."}},
    summary="Liveness",
    tags=["operations"],
)
async def health(service: Service) -> JSONResponse:
    """Cheap liveness check that never touches a model, with recent /register latency percentiles and
    each model's queue.

    503 once warm-up has failed, a state the process does not leave by itself, so that a liveness
    probe restarts it rather than leaving it alive and never ready.
    """
    answer = HealthResponse(
        status="failed" if service.warmup_error else "ok",
        detail=service.warmup_error,
        ready=service.ready.is_set(),
        uptime_s=time.monotonic() - service.started_at,
        queue_depth=sum(model.queue_depth for model in service.models.values()),
        in_flight=service.in_flight,
        latency=LatencySummary(**service.latency.summary()),
        models=[
            ModelHealth(
                name=name,
                version=model.info.version,
                ready=service.ready.is_set(),
                queue_depth=model.queue_depth,
            )
            for name, model in service.models.items()
        ],
    )
    return JSONResponse(answer.model_dump(), status_code=503 if service.warmup_error else 200)


@router.get(
    "/ready",
    response_model=ReadyResponse,
    responses={503: {"model": ReadyResponse, "description": "Models not loaded or not warmed up yet."}},
    summary="Readiness",
    tags=["operations"],
)
async def ready(service: Service) -> JSONResponse:
    """200 once every model is loaded and warmed up at every batch size; 503 before (and while stopping)."""
    if service.ready.is_set():
        return JSONResponse(
            ReadyResponse(ready=True, detail=f"models loaded and warmed up: {', '.join(service.models)}").model_dump()
        )
    detail = service.warmup_error or (
        "loading the models" if not service.models else "warming up the models" if service.accepting else "stopping"
    )
    return JSONResponse(ReadyResponse(ready=False, detail=detail).model_dump(), status_code=503)


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {"example": 'ifnet_batch_size_bucket{le="1.0"} 12.0\n'}}}},
    summary="Prometheus metrics",
    tags=["operations"],
)
async def metrics(service: Service) -> Response:
    """Request counts by status and latency; per model (label `model`) queue wait, batch size, inference
    time and answers; in Prometheus text format."""
    body, content_type = service.metrics.render()
    return Response(body, media_type=content_type)
