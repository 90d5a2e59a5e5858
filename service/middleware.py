"""Request body size limit, enforced before and while the body arrives."""

import json

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send


class BodyTooLarge(HTTPException):
    def __init__(self, limit: int):
        super().__init__(413, f"body: request body is larger than the limit of {limit} bytes; send fewer points")


class BodyLimitMiddleware:
    """Answers 413 when a body exceeds `max_bytes`.

    A declared Content-Length is checked before anything is read; chunked bodies are counted as
    they stream in, and reading stops at the limit. The exception raised from `receive` is an
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
