"""uvicorn's HTTP/1.1 protocol (h11) and server with four guards for the service's connections.

Head deadline: uvicorn bounds only the idle time between requests (its keep-alive timeout, reset
by every byte received), so a client that connects and sends nothing, or trickles a request's
headers, holds its connection open forever (slowloris). The request timeout cannot help: it starts
once the app has the request, that is once its head is complete. Here a connection that has not
completed a request head within `head_timeout_s` of opening, or of its previous response, is
closed: with a 408 if part of a head had arrived, silently if nothing had. A request body is
bounded by the request timeout.

Head size: h11 refuses a head over its limit (uvicorn's `h11_max_incomplete_event_size`) only
while the head is incomplete; one that arrives whole in a single read is accepted at any size.
Here a head longer than `max_head_bytes` gets 431 however it arrives; run uvicorn with the same
value as its h11 limit so that a head spread over several reads meets the same bound
(`python -m service` does).

Lingering close: the service answers some requests before reading their body (401, 404, 405,
413 on the declared length, 429). No further request can follow on such a connection until the
client has sent the rest of that body, and uvicorn's idle timer, stopped by every byte that
arrives, would let a client that trickles it hold the connection forever; so the connection is
closed once the answer is out, and the answer says so (`connection: close`): a client that has
sent the whole body by the time it reads the answer would otherwise keep the connection for its
next request, and where the server's end came a moment after the answer, that request met the
closed connection. When a connection must close, uvicorn closes it at once, and the
kernel answers the body still arriving with a reset, which most clients report instead of the
answer. Here the connection first shuts its sending
side and reads and drops up to `max_drain_bytes` more for at most `drain_timeout_s`, as nginx's
lingering close does, so that the client reads the answer.

Shutdown (`ServiceServer`): uvicorn asks the connections open when its graceful shutdown starts to
close once their answer is out. A connection accepted just before, whose protocol starts just
after, was never asked: it kept serving its client until the graceful timeout, whose cancelled
request ended in a 500. Here every connection that opens during the shutdown is asked too.

The subclasses reach into uvicorn's H11Protocol and Server and h11's connection state, which neither
promises to keep: pyproject.toml pins both to TESTED_VERSIONS, and tests/service/test_security.py
fails on any other installed version. To upgrade, widen both together once the protocol tests pass.
"""

import asyncio
import logging

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.server import Server

from service.settings import Settings

logger = logging.getLogger("service.protocol")
TESTED_VERSIONS = {"uvicorn": ">=0.55,<0.56", "h11": ">=0.16,<0.17"}


def _default(setting: str):
    """A setting's default: the limits of the class as given to plain uvicorn (`--http`)."""
    return Settings.model_fields[setting].default


def _plain_response(status: str, text: bytes) -> bytes:
    return (
        b"HTTP/1.1 %s\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
        b"content-length: %d\r\n\r\n%s" % (status.encode(), len(text), text)
    )


class _LingeringTransport:
    """The connection's transport as uvicorn sees it: close() lets the protocol drain first."""

    def __init__(self, transport: asyncio.Transport, protocol: "ServiceProtocol"):
        self._transport = transport
        self._protocol = protocol

    def close(self) -> None:
        self._protocol._close_when_drained()

    def is_closing(self) -> bool:
        return self._protocol._draining or self._transport.is_closing()

    def __getattr__(self, name: str):
        return getattr(self._transport, name)


class _Connection(h11.Connection):
    """h11's server side of a connection, whose answers given before the request's body has arrived
    say `connection: close` (the connection closes after them)."""

    def send(self, event):
        if isinstance(event, h11.Response) and self.their_state is h11.SEND_BODY:
            headers = [(name, value) for name, value in event.headers if name != b"connection"]
            event = h11.Response(
                status_code=event.status_code, headers=[*headers, (b"connection", b"close")], reason=event.reason
            )
        return super().send(event)


class ServiceProtocol(H11Protocol):
    head_timeout_s: float = _default("request_head_timeout_s")
    max_head_bytes: int = _default("max_head_bytes")
    max_drain_bytes: int = _default("max_body_bytes")
    drain_timeout_s: float = 10.0

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.conn = _Connection(h11.SERVER, self.conn._max_incomplete_event_size)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self._head_deadline: asyncio.TimerHandle | None = None
        self._socket = transport
        self._draining = False
        self._drained = 0
        super().connection_made(_LingeringTransport(transport, self))  # type: ignore[arg-type]
        self._arm_head_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_head_deadline()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._draining:  # the rest of a body nobody will read
            self._drained += len(data)
            if self._drained > self.max_drain_bytes:
                self._socket.close()
            return
        if self.conn.their_state is h11.IDLE and self._head_size(data) > self.max_head_bytes:
            self._refuse(
                "431 Request Header Fields Too Large",
                b"request head larger than %d bytes; send fewer or shorter headers\n" % self.max_head_bytes,
                f"request head over {self.max_head_bytes} bytes",
            )
            return
        super().data_received(data)

    def on_response_complete(self) -> None:
        # Armed before uvicorn goes on to a pipelined request; a head that is complete by the
        # deadline leaves the connection busy, and the deadline then does nothing.
        self._arm_head_deadline()
        super().on_response_complete()
        if self.conn.their_state is h11.SEND_BODY:  # answered before the body ended: no next request can follow
            self._close_when_drained()

    def _close_when_drained(self) -> None:
        """Close now, or, while the client is still sending a request body, once it has stopped."""
        if self._draining or self._socket.is_closing():
            return
        if self.conn.their_state is not h11.SEND_BODY or not self._socket.can_write_eof():
            self._socket.close()
            return
        self._draining = True
        self._disarm_head_deadline()
        self._socket.write_eof()  # the answer goes out, then our side of the connection ends
        self._socket.resume_reading()  # uvicorn pauses reading while a body waits for the app
        self.loop.call_later(self.drain_timeout_s, self._socket.close)

    def _head_size(self, data: bytes) -> int:
        """Bytes of the head being received, counting only up to max_head_bytes + 1 of it."""
        buffered, _ = self.conn.trailing_data  # an incomplete head from earlier reads
        received = buffered + data[: self.max_head_bytes + 4]
        end = received.find(b"\r\n\r\n", 0, self.max_head_bytes + 4)
        return end + 4 if end >= 0 else len(received)

    def _arm_head_deadline(self) -> None:
        self._disarm_head_deadline()
        self._head_deadline = self.loop.call_later(self.head_timeout_s, self._head_timed_out)

    def _disarm_head_deadline(self) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
            self._head_deadline = None

    def _head_timed_out(self) -> None:
        self._head_deadline = None
        if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:  # a head has arrived
            return
        partial_head, _ = self.conn.trailing_data
        if not partial_head:
            self._socket.close()  # nothing was asked, so nothing to answer
            return
        self._refuse(
            "408 Request Timeout",
            b"request headers not received within the timeout; send the whole head at once\n",
            f"request head incomplete after {self.head_timeout_s:g} s ({len(partial_head)} bytes)",
        )

    def _refuse(self, status: str, text: bytes, reason: str) -> None:
        client = "{}:{}".format(*self.client) if self.client else "?"
        logger.warning("closing a connection from %s: %s", client, reason)
        self._socket.write(_plain_response(status, text))
        self._socket.close()


def service_protocol(settings: Settings) -> type[ServiceProtocol]:
    """The protocol class to give uvicorn (`http=`), with the limits of these settings."""
    limits = {
        "head_timeout_s": settings.request_head_timeout_s,
        "max_head_bytes": settings.max_head_bytes,
        "max_drain_bytes": settings.max_body_bytes,
    }
    return type("ServiceProtocol", (ServiceProtocol,), limits)


class ServiceServer(Server):
    """uvicorn's server, whose graceful shutdown also asks connections that open meanwhile to close."""

    async def shutdown(self, sockets=None) -> None:
        asked = set(self.server_state.connections)  # uvicorn asks these, its listeners closed first
        latecomers = asyncio.create_task(self._ask_latecomers(asked))
        try:
            await super().shutdown(sockets)
        finally:
            latecomers.cancel()

    async def _ask_latecomers(self, asked: set) -> None:
        while True:
            await asyncio.sleep(0.05)
            for connection in set(self.server_state.connections) - asked:
                asked.add(connection)
                connection.shutdown()
