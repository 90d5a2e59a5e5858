"""ASGI middleware: request ids, the API key beyond inference, the body size limit (before and while
reading), compressed bodies."""

import json
import re
import secrets
import uuid
import zlib

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

# A client's own id is kept only if it is a plain token, so that it cannot forge log lines or headers.
CLIENT_REQUEST_ID = re.compile(r"[A-Za-z0-9._:-]{1,128}")


class RequestIdMiddleware:
    """Gives every request an id, in `request.state.request_id` and in the answer's `X-Request-ID`.

    The id is the client's `X-Request-ID` when that is a plain token (letters, digits, `._:-`, at
    most 128), else a new random one; a 500 names it, and the log line about that failure has it,
    so that a failed request a user reports can be found in the log.
    """

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        given = dict(scope.get("headers") or []).get(b"x-request-id", b"").decode("latin-1")
        request_id = given if CLIENT_REQUEST_ID.fullmatch(given) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = request_id  # shared with every copy of the scope
        header = (b"x-request-id", request_id.encode())

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []), header]}
            await send(message)

        await self.app(scope, receive, send_with_id)


def request_id(scope: Scope) -> str | None:
    """The id RequestIdMiddleware gave this request (None outside it)."""
    return (scope.get("state") or {}).get("request_id")


def body_received(scope: Scope) -> bool:
    """Whether the whole request body has arrived (as BodyLimitMiddleware saw it)."""
    return bool((scope.get("state") or {}).get("body_received"))


class BodyTooLarge(HTTPException):
    def __init__(self, limit: int):
        super().__init__(413, f"body: request body is larger than the limit of {limit} bytes; send fewer points")


class BodyLimitMiddleware:
    """Answers 413 when a body exceeds `max_bytes`.

    A declared Content-Length is checked before anything is read; chunked bodies are counted as
    they stream in, and reading stops at the limit. It also notes when the body has arrived
    whole (`body_received`), so that a request over its deadline can be told apart as the
    client's (408, body still arriving) or the service's (504). The exception raised from `receive` is an
    HTTPException so that FastAPI's body parsing lets it through unchanged.
    """

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        v2 = scope["path"].startswith("/v2")  # the v2 routes' errors are {"error": ...}
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            await self._reject(send, v2)
            return
        received = 0
        response_started = False

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes)
                if not message.get("more_body", False):
                    scope.setdefault("state", {})["body_received"] = True
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal response_started
            if message["type"] == "http.response.start":
                response_started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyTooLarge:
            if response_started:
                raise
            await self._reject(send, v2)

    async def _reject(self, send: Send, v2: bool) -> None:
        detail = BodyTooLarge(self.max_bytes).detail
        answer = {"error": detail} if v2 else {"detail": detail, "errors": [{"field": "body", "problem": detail[6:]}]}
        body = json.dumps(answer).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
            }
        )
        await send({"type": "http.response.body", "body": body})


# Content-Encoding -> zlib's wbits: gzip's header and trailer, or the zlib wrapper HTTP's deflate means.
INFLATABLE = {"gzip": 16 + zlib.MAX_WBITS, "x-gzip": 16 + zlib.MAX_WBITS, "deflate": zlib.MAX_WBITS}


class ContentEncodingMiddleware:
    """Inflates request bodies sent with `Content-Encoding: gzip` or `deflate` as they arrive.

    The app sees the plain body (without the encoding and length headers). The inflated size is
    held to `max_bytes` chunk by chunk, so a small body that inflates hugely (a zip bomb) is
    refused with 413 without ever being expanded in memory. Other encodings get 415 and bad
    compressed data 400, raised when the body is first read, so that a missing API key still gets
    its 401 first (the rest of a refused body is dropped by the connection, service.protocol).
    Runs inside BodyLimitMiddleware, which limits the bytes on the wire.
    """

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = (scope.get("headers") or []) if scope["type"] == "http" else []
        encoding = next((value for name, value in headers if name == b"content-encoding"), None)
        if encoding is None:
            await self.app(scope, receive, send)
            return
        name = encoding.decode("latin-1").strip().lower()
        plain = [(key, value) for key, value in headers if key not in (b"content-encoding", b"content-length")]
        scope = {**scope, "headers": plain}
        if name != "identity":
            receive = _inflating(receive, name, self.max_bytes)
        await self.app(scope, receive, send)


def _inflating(receive: Receive, encoding: str, max_bytes: int) -> Receive:
    if encoding not in INFLATABLE:
        supported = ", ".join(sorted(INFLATABLE))

        async def refuse() -> Message:
            raise HTTPException(
                415, f"content-encoding: {encoding!r} is not supported; send the body plain or as {supported}"
            )

        return refuse

    inflater = zlib.decompressobj(INFLATABLE[encoding])
    room = max_bytes  # inflated bytes still allowed

    def inflate(data: bytes) -> bytes:
        nonlocal room
        pieces = []
        while data:
            try:
                piece = inflater.decompress(data, room + 1)  # never more than one byte over the limit
            except zlib.error as error:
                raise HTTPException(400, f"body: not valid {encoding} data ({error})") from None
            room -= len(piece)
            if room < 0:
                raise HTTPException(
                    413,
                    f"body: the request body inflates to more than the limit of {max_bytes} bytes; send fewer points",
                )
            pieces.append(piece)
            data = inflater.unconsumed_tail
        return b"".join(pieces)

    async def inflating_receive() -> Message:
        message = await receive()
        if message["type"] != "http.request":
            return message
        body = inflate(message.get("body", b""))
        if not message.get("more_body", False) and (not inflater.eof or inflater.unused_data):
            problem = "ends before its end" if not inflater.eof else "has data after its end"
            raise HTTPException(400, f"body: the {encoding} stream {problem}; send the whole body, compressed once")
        return {**message, "body": body}

    return inflating_receive


# Open whatever the API key's scope: what liveness and readiness probes call.
PROBE_PATH = re.compile(r"/health|/ready|/v2/health/(live|ready)|/v2/models/[^/]+/ready")


class ApiKeyMiddleware:
    """With IFNET_API_KEY_SCOPE=all, every route but the probes needs the API key: /metrics,
    /docs, /openapi.json and /v2/models/{name} (which shows the model's hashes) included.
    /register and v2 inference check the key themselves (service.dependencies) either way."""

    def __init__(self, app: ASGIApp, api_key: str):
        self.app = app
        self.api_key = api_key.encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or PROBE_PATH.fullmatch(scope["path"]) or self._has_key(scope):
            await self.app(scope, receive, send)
            return
        detail = "missing or wrong API key: send it in the X-API-Key header (or Authorization: Bearer <key>)"
        v2 = scope["path"].startswith("/v2")
        answer = {"error": detail} if v2 else {"detail": detail, "errors": []}
        body = json.dumps(answer).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"www-authenticate", b"Bearer"),
        ]
        await send({"type": "http.response.start", "status": 401, "headers": headers})
        await send({"type": "http.response.body", "body": body})

    def _has_key(self, scope: Scope) -> bool:
        headers = dict(scope.get("headers") or [])
        key = headers.get(b"x-api-key")
        bearer = headers.get(b"authorization", b"")
        if key is None and bearer[:7].lower() == b"bearer ":
            key = bearer[7:].strip()
        return key is not None and secrets.compare_digest(key, self.api_key)
