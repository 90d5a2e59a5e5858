"""uvicorn's HTTP/1.1 protocol (h11) with a deadline on every request head.

uvicorn bounds only the idle time between requests (its keep-alive timeout, reset by every byte
received), so a client that connects and sends nothing, or trickles a request's headers, holds its
connection open forever (slowloris). The request timeout cannot help: it starts once the app has
the request, that is once its head is complete. Here a connection that has not completed a request
head within `head_timeout_s` of opening, or of its previous response, is closed: with a 408 if part
of a head had arrived, silently if nothing had. A request body is bounded by the request timeout.
"""

import asyncio
import logging

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

logger = logging.getLogger("service.protocol")

_TIMEOUT_TEXT = b"request headers not received within the timeout; send the whole head at once\n"
REQUEST_TIMEOUT_RESPONSE = (
    b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
    b"content-length: %d\r\n\r\n%s" % (len(_TIMEOUT_TEXT), _TIMEOUT_TEXT)
)


class HeadDeadlineProtocol(H11Protocol):
    head_timeout_s: float = 10.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self._head_deadline: asyncio.TimerHandle | None = None
        super().connection_made(transport)
        self._arm_head_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_head_deadline()
        super().connection_lost(exc)

    def on_response_complete(self) -> None:
        # Armed before uvicorn goes on to a pipelined request; a head that is complete by the
        # deadline leaves the connection busy, and the deadline then does nothing.
        self._arm_head_deadline()
        super().on_response_complete()

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
        if partial_head:
            logger.warning(
                "closing a connection from %s: request head incomplete after %g s (%d bytes)",
                "{}:{}".format(*self.client) if self.client else "?",
                self.head_timeout_s,
                len(partial_head),
            )
            self.transport.write(REQUEST_TIMEOUT_RESPONSE)
        self.transport.close()


def head_deadline_protocol(head_timeout_s: float) -> type[HeadDeadlineProtocol]:
    """The protocol class to give uvicorn (`http=`), with this deadline."""
    return type("HeadDeadlineProtocol", (HeadDeadlineProtocol,), {"head_timeout_s": head_timeout_s})
