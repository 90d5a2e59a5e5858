"""The /register body in any accepted encoding: JSON, multipart file parts, or a raw NPY/NPZ body."""

import asyncio
import contextlib
import errno
from collections.abc import Callable, Iterator
from typing import TypeVar

import numpy as np
from fastapi import HTTPException
from pydantic import BaseModel, ValidationError
from starlette.datastructures import UploadFile
from starlette.requests import Request

from service.formats import UnsupportedFormat, read_cloud, read_pair
from service.schemas import RegisterRequest, RegistrationOptions
from service.settings import Settings
from service.validation import InvalidInput, invalid_request

Model = TypeVar("Model", bound=BaseModel)
T = TypeVar("T")

JSON_TYPES = ("application/json",)
MULTIPART_TYPES = ("multipart/form-data",)
RAW_TYPES = ("application/x-npy", "application/x-npz", "application/zip", "application/octet-stream")
ACCEPTED = (
    "application/json, multipart/form-data (file parts `source` and `target`), application/x-npy or application/x-npz"
)


class UnsupportedMediaType(HTTPException):
    def __init__(self, detail: str):
        super().__init__(415, detail)


# Parsing builds Python objects under the GIL, so large bodies parsed side by side gain nothing and
# each holds its objects meanwhile: they take turns. Small bodies never wait.
LARGE_JSON_BYTES = 1 << 20
LARGE_BODY_BYTES = LARGE_JSON_BYTES


async def parse_in_thread(request: Request, size: int, parse: Callable[..., T], *args) -> T:
    """Run `parse(*args)` in a worker thread; bodies over LARGE_BODY_BYTES one at a time.

    A request whose deadline passes while it waits for its turn never starts parsing, so the
    worker threads stay free for requests that can still be answered.
    """
    if size <= LARGE_BODY_BYTES:
        return await asyncio.to_thread(parse, *args)
    async with request.app.state.service.large_json_parse:
        return await asyncio.to_thread(parse, *args)


async def parse_json(request: Request, schema: type[Model]) -> Model:
    """Validate a JSON body in a worker thread: a 100k-point body takes a while and must not stall
    the event loop (health checks, other clients). Bodies over LARGE_JSON_BYTES are parsed one at
    a time. Raises RequestValidationError (422)."""
    body = await request.body()
    try:
        return await parse_in_thread(request, len(body), schema.model_validate_json, body)
    except ValidationError as error:
        raise invalid_request(error) from None


def media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


async def read_register_body(
    request: Request, query_options: str | None, settings: Settings
) -> tuple[np.ndarray, np.ndarray, RegistrationOptions]:
    """Source, target and options of a /register request, whatever its content type.

    Raises UnsupportedMediaType (415), InvalidInput or RequestValidationError (422).
    """
    unknown = sorted(set(request.query_params) - {"options"})
    if unknown:
        raise InvalidInput(
            unknown[0],
            "unknown query parameter; put options in the JSON body (or in `?options=<JSON>` for NPY/NPZ bodies)",
        )
    media = media_type(request)
    if media in JSON_TYPES or media.endswith("+json"):
        if query_options is not None:
            raise InvalidInput("options", "with a JSON body, put the options in the body, not in the query string")
        payload = await parse_json(request, RegisterRequest)
        return payload.source, payload.target, payload
    if media in MULTIPART_TYPES:
        return await _read_multipart(request, query_options, settings)
    if media in RAW_TYPES:
        body = await request.body()
        try:
            source, target = await parse_in_thread(request, len(body), read_pair, body, settings.max_cloud_points)
        except UnsupportedFormat as error:
            raise UnsupportedMediaType(str(error)) from None
        return source, target, _options(query_options)
    shown = media or "none"
    raise UnsupportedMediaType(f"content-type: {shown!r} is not accepted; send {ACCEPTED}")


async def _read_multipart(
    request: Request, query_options: str | None, settings: Settings
) -> tuple[np.ndarray, np.ndarray, RegistrationOptions]:
    with _spooling_space():
        async with request.form(max_files=3, max_fields=3) as form:  # source, target and options (field or file)
            unexpected = sorted(set(form.keys()) - {"source", "target", "options"})
            if unexpected:
                raise InvalidInput(
                    unexpected[0],
                    "unexpected form part; send file parts `source` and `target` and optionally `options` (JSON)",
                )
            clouds = []
            for name in ("source", "target"):
                part = form.get(name)
                if not isinstance(part, UploadFile):
                    raise InvalidInput(
                        name, f"missing file part: upload the cloud as a PLY, PCD or NPY file named `{name}`"
                    )
                data = await part.read()
                try:
                    cloud = await parse_in_thread(
                        request, len(data), read_cloud, data, name, settings.max_cloud_points, settings.max_body_bytes
                    )
                    clouds.append(cloud)
                except UnsupportedFormat as error:
                    raise UnsupportedMediaType(str(error)) from None
            options_field = form.get("options")
            if isinstance(options_field, UploadFile):
                options_field = (await options_field.read()).decode("utf-8", errors="replace")
    if options_field is not None and query_options is not None:
        raise InvalidInput("options", "given both as a form field and in the query string; send it once")
    return clouds[0], clouds[1], _options(options_field if options_field is not None else query_options)


@contextlib.contextmanager
def _spooling_space() -> Iterator[None]:
    """Multipart files over 1 MB are spooled to /tmp: a full /tmp is the server's state, not the
    client's fault, so it answers 503 (retry) rather than 500."""
    try:
        yield
    except OSError as error:
        if error.errno != errno.ENOSPC:
            raise
        raise HTTPException(
            503, "body: no room on the server to buffer this upload right now; retry shortly", {"Retry-After": "1"}
        ) from None


def _options(text: str | None) -> RegistrationOptions:
    if text is None or not text.strip():
        return RegistrationOptions()
    try:
        return RegistrationOptions.model_validate_json(text)
    except ValidationError as error:
        unreadable = [e for e in error.errors() if e["type"] == "json_invalid"]
        if unreadable:
            reason = (unreadable[0].get("ctx") or {}).get("error", "")
            example = '{"refine": true}'
            raise InvalidInput("options", f"is not valid JSON ({reason}); send an object like {example}") from None
        raise invalid_request(error) from None
