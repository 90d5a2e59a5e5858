"""The FastAPI application: factory, lifespan (load the models, warm up, drain on shutdown) and error answers."""

import asyncio
import logging
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from fastapi_offline import FastAPIOffline
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from service import __version__
from service.batcher import InferenceError, QueueFullError, RequestTimeoutError, ShuttingDownError
from service.engine import Engine, load_models
from service.formats import UnsupportedFormat
from service.metrics import HttpMetricsMiddleware
from service.middleware import (
    ApiKeyMiddleware,
    BodyLimitMiddleware,
    ContentEncodingMiddleware,
    RequestIdMiddleware,
    body_received,
    request_id,
)
from service.oip import router as oip_router
from service.registration import ClientDisconnected, RegistrationFailed
from service.routes import router
from service.schemas import RegisterRequest, V2InferRequest
from service.settings import Settings
from service.state import ServiceState
from service.validation import InvalidInput

logger = logging.getLogger(__name__)
FIELD_NAME = re.compile(r"[a-z][a-z_-]*(\[\d+\])?")  # body, source, content-type, target[1], ...

DESCRIPTION = """
Rigid registration of two point clouds with IFNet, run by ONNX Runtime.

`POST /register` returns (R, t) with `target ~ source @ R^T + t` in the clouds' own units, plus
Open3D-style fitness and inlier RMSE. The option `model` picks one of the served networks
(`GET /v2/models`). Requests are batched; `/health`, `/ready` and `/metrics` serve operations,
and `/v2/...` speaks the Open Inference Protocol.
"""


async def _become_ready(state: ServiceState) -> None:
    """Start feature matching's child process, warm each model up at every batch size, one after
    another (their calls would contend for the CPUs), then start serving the queues and report ready."""
    batchers = [batcher for model in state.models.values() for batcher in model.batchers]
    if state.settings.warmup and state.feature_match is not None:
        try:
            await asyncio.to_thread(state.feature_match.start)
        except Exception as error:
            state.warmup_error = f"feature matching's process failed to start: {error}"
            logger.exception("feature matching's process failed to start; the service stays not ready")
            return
    for batcher in batchers:
        try:
            if state.settings.warmup:
                await batcher.warm_up(batcher.engine.info.network_points)
        except Exception as error:
            state.warmup_error = f"warm-up of model {batcher.model} failed: {error}"
            logger.exception("warm-up of model %s failed; the service stays not ready", batcher.model)
            return
    for batcher in batchers:
        batcher.start()
    state.ready.set()
    state.metrics.ready.set(1)


def _lifespan(engines: list[Engine] | None):
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state: ServiceState = app.state.service
        settings = state.settings
        # A missing or corrupt model file raises ModelLoadError here, so startup fails with its message.
        state.serve(engines or await asyncio.to_thread(load_models, settings))
        state.accepting = True  # again, where the app is started anew (a test client per request)
        becoming_ready = asyncio.create_task(_become_ready(state))
        try:
            yield
        finally:
            # The server has stopped accepting connections and waited for in-flight requests;
            # finish whatever is still queued, then stop the worker.
            state.accepting = False
            state.ready.clear()
            state.metrics.ready.set(0)
            becoming_ready.cancel()
            await asyncio.wait({becoming_ready})
            batchers = [batcher for model in state.models.values() for batcher in model.batchers]
            await asyncio.gather(*(batcher.close(settings.shutdown_timeout_s) for batcher in batchers))
            if state.feature_match is not None:
                state.feature_match.close()
            logger.info("batchers drained; shutting down")
            state.metrics.worker_stopped()

    return lifespan


def _error(request: Request, status: int, detail: str, errors=(), headers: dict | None = None) -> JSONResponse:
    """One error shape per API: {"error": ...} on the v2 routes, {"detail", "errors"} elsewhere."""
    if request.url.path.startswith("/v2"):
        return JSONResponse({"error": detail}, status_code=status, headers=headers)
    return JSONResponse({"detail": detail, "errors": list(errors)}, status_code=status, headers=headers)


def _field_errors(errors: list[dict]) -> list[dict[str, str]]:
    found = []
    for error in errors:
        if error.get("type") == "json_invalid":
            reason = (error.get("ctx") or {}).get("error") or error.get("msg", "")
            found.append({"field": "body", "problem": f"invalid JSON: {reason}"})
            continue
        location = [str(part) for part in error.get("loc", ()) if part not in ("body", "query", "path", "header")]
        found.append({"field": ".".join(location) or "body", "problem": error.get("msg", "invalid")})
    return found


def _install_error_handlers(app: FastAPI) -> None:
    def validation_failed(request: Request, errors: list[dict]) -> JSONResponse:
        fields = _field_errors(errors)
        detail = "; ".join(f"{item['field']}: {item['problem']}" for item in fields[:5])
        if len(fields) > 5:
            detail += f"; and {len(fields) - 5} more"
        return _error(request, 422, detail, fields)

    @app.exception_handler(RequestValidationError)
    async def on_request_validation(request: Request, error: RequestValidationError) -> JSONResponse:
        return validation_failed(request, list(error.errors()))

    @app.exception_handler(InvalidInput)
    async def on_invalid_input(request: Request, error: InvalidInput) -> JSONResponse:
        return _error(request, 422, str(error), [{"field": error.field, "problem": error.problem}])

    @app.exception_handler(UnsupportedFormat)
    async def on_unsupported_format(request: Request, error: UnsupportedFormat) -> JSONResponse:
        return _error(request, 415, str(error))

    @app.exception_handler(RegistrationFailed)
    async def on_registration_failed(request: Request, error: RegistrationFailed) -> JSONResponse:
        return _error(request, 422, str(error))

    @app.exception_handler(QueueFullError)
    async def on_queue_full(request: Request, error: QueueFullError) -> JSONResponse:
        return _error(request, 429, str(error), headers={"Retry-After": str(error.retry_after_s)})

    @app.exception_handler(RequestTimeoutError)
    async def on_timeout(request: Request, error: RequestTimeoutError) -> JSONResponse:
        if not body_received(request.scope):  # the client was too slow, not the service
            timeout = request.app.state.service.settings.request_timeout_s
            detail = f"body: not received within the request timeout of {timeout:g} s; send the whole body at once"
            return _error(request, 408, detail, [{"field": "body", "problem": detail[6:]}], {"Connection": "close"})
        return _error(request, 504, str(error))

    @app.exception_handler(ShuttingDownError)
    async def on_shutting_down(request: Request, error: ShuttingDownError) -> JSONResponse:
        return _error(request, 503, f"{error}; retry on another instance", headers={"Retry-After": "1"})

    @app.exception_handler(ClientDisconnected)
    @app.exception_handler(ClientDisconnect)  # gone while its body was still arriving
    async def on_disconnect(request: Request, error: Exception) -> JSONResponse:
        return _error(request, 499, str(error))  # nobody reads it; recorded in the metrics as 499

    @app.exception_handler(InferenceError)
    async def on_inference_error(request: Request, error: InferenceError) -> JSONResponse:
        return _error(request, 500, f"internal error: {error}")

    # Anything unforeseen: still a JSON answer. Starlette re-raises the error after this answer, so
    # the server logs its traceback as usual.
    @app.exception_handler(Exception)
    async def on_unexpected(request: Request, error: Exception) -> JSONResponse:
        # Answered outside the middleware stack, so the id header is added here.
        identifier = request_id(request.scope)
        logger.error("request %s (%s %s) failed: %r", identifier, request.method, request.url.path, error)
        detail = f"internal error; the server log has the details under request id {identifier}"
        return _error(request, 500, detail, headers={"X-Request-ID": identifier} if identifier else None)

    # Starlette's class, not FastAPI's subclass: FastAPI and Starlette raise the base class themselves
    # (404, 405, unparseable bodies), and those answers must have the same shape as every other error.
    @app.exception_handler(StarletteHTTPException)
    async def on_http_exception(request: Request, error: StarletteHTTPException) -> JSONResponse:
        detail = str(error.detail)
        field, separator, problem = detail.partition(": ")  # the service's own "<field>: <problem>" details
        errors = [{"field": field, "problem": problem}] if separator and FIELD_NAME.fullmatch(field) else []
        return _error(request, error.status_code, detail, errors, headers=getattr(error, "headers", None))


def _install_openapi(app: FastAPI) -> None:
    """Add the JSON request schemas of the routes that parse their bodies by hand: /register (for
    the binary formats) and v2 inference (to check the API key before reading the body)."""

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for body_model in (RegisterRequest, V2InferRequest):
                request_schema = body_model.model_json_schema(ref_template="#/components/schemas/{model}")
                components.update(request_schema.pop("$defs", {}))
                components[body_model.__name__] = request_schema
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi


def create_app(settings: Settings | None = None, engines: list[Engine] | None = None) -> FastAPI:
    """The service as an ASGI app, serving `engines` (the first is the default model); without them,
    the lifespan loads the model repository (`engine.load_models`)."""
    settings = settings or Settings()
    state = ServiceState(settings)
    # /docs and /redoc load Swagger UI and ReDoc from the installed package, never from a CDN; no
    # trailing-slash redirects, whose Location would be built from the client's Host header.
    app = FastAPIOffline(
        title="ifnet-serve",
        version=__version__,
        description=DESCRIPTION,
        lifespan=_lifespan(engines),
        redirect_slashes=False,
    )
    app.state.service = state
    app.include_router(router)
    app.include_router(oip_router)
    _install_error_handlers(app)
    _install_openapi(app)
    # Outermost last: metrics see every answer, including the body limit's 413; the limit counts the
    # bytes on the wire, the inflater (inside it) the bytes a compressed body expands to.
    app.add_middleware(ContentEncodingMiddleware, max_bytes=settings.max_body_bytes)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes)
    if settings.api_key is not None and settings.api_key_scope == "all":
        app.add_middleware(ApiKeyMiddleware, api_key=settings.api_key.get_secret_value())
    static_routes = {route.path for route in (*router.routes, *oip_router.routes) if "{" not in route.path}
    app.add_middleware(
        HttpMetricsMiddleware,
        metrics=state.metrics,
        window=state.latency,
        windowed_routes={"/register"},
        static_routes=static_routes,
    )
    app.add_middleware(RequestIdMiddleware)  # every answer but an unforeseen error's 500 (its handler adds the id)
    return app
