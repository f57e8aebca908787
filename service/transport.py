"""uvicorn's HTTP and WebSocket protocols with deadlines for slow and dead peers, and the one
`uvicorn.Config` every way of serving the app uses (`stylestream serve`, workers, the tests).

Stock uvicorn waits on a peer for ever in two places:

- a connection that never finishes its request headers (or sends nothing) is held open: there
  is no header-read timeout, so a few thousand half-open connections pin as many descriptors;
- a WebSocket send waits for the socket to drain, and a close flushes before it lets go, so a
  client that stops reading holds its session, its send lock and its buffers until it leaves.

`GuardedHttp` closes a connection whose request headers are not complete within
`header_timeout_s` (to 1.5x it, spread so a burst is not dropped all at once) of its start (or of
the request's first byte on a kept-alive connection);
`GuardedWebSocket` aborts a connection whose outgoing data does not drain within
`send_timeout_s` (the app's receive then sees a disconnect, so the session is freed and kept
for resume), and aborts rather than flushes a closing handshake the peer has not answered within
`send_timeout_s`, and stops reading from a client it closed for flooding (4429).
"""

from __future__ import annotations

import asyncio
import random
from typing import Any

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.utils import ClientDisconnected
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from .limits import CLOSE_FLOODING
from .settings import ServiceSettings

FLOOD_CLOSE_GRACE_S = 1.0  # time for the close frame to reach a client closed for flooding
# Each connection's header deadline is header_timeout_s times 1 .. 1 + this (uniform): connections
# opened together (2,000 half-open ones in a burst) are then not all aborted in one pass of the
# event loop, which held the healthy sessions' frames (hostile_bench half-open phase, p99 / quiet
# 1.07-4.91 in three runs at one deadline, 0.81-1.14 spread)
HEADER_DEADLINE_SPREAD = 0.5


class GuardedHttp(HttpToolsProtocol):
    header_timeout_s = 10.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._header_timer: asyncio.TimerHandle | None = None
        self._arm_header_timer()

    def _arm_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
        deadline = self.header_timeout_s * (1.0 + HEADER_DEADLINE_SPREAD * random.random())
        self._header_timer = self.loop.call_later(deadline, self._headers_too_slow)

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        if not self.transport.is_closing():
            self.transport.abort()  # nothing of ours is waiting to be written: no response was started

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._arm_header_timer()  # a kept-alive connection's next request

    def on_headers_complete(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        super().connection_lost(exc)


class GuardedWebSocket(WebSocketsSansIOProtocol):
    send_timeout_s = 10.0

    async def send(self, message: Any) -> None:
        if not self.writable.is_set():
            try:
                async with asyncio.timeout(self.send_timeout_s):
                    await self.writable.wait()
            except TimeoutError:
                self.transport.abort()  # connection_lost follows: the app's receive gets its disconnect
                raise ClientDisconnected() from None
        await super().send(message)
        if self.close_timer is not None:  # our close was sent: a peer that does not answer in time is dropped
            self.close_timer.cancel()
            grace = self.send_timeout_s
            if message.get("code") == CLOSE_FLOODING and not self.transport.is_closing():
                # closed for flooding: read nothing more from it (parsing a flood's frames after the
                # close still cost the event loop) and let it go soon, without waiting for its close
                self.transport.pause_reading()
                grace = min(grace, FLOOD_CLOSE_GRACE_S)
            self.close_timer = self.loop.call_later(grace, self.transport.abort)

    def keepalive_timeout(self) -> None:
        super().keepalive_timeout()  # it closes, which flushes first: a peer that does not read is aborted instead
        self.transport.abort()


def guarded_protocols(settings: ServiceSettings) -> tuple[type[GuardedHttp], type[GuardedWebSocket]]:
    """The two protocol classes with this server's deadlines (uvicorn instantiates them itself)."""
    http = type("GuardedHttp", (GuardedHttp,), {"header_timeout_s": settings.header_timeout_s})
    ws = type("GuardedWebSocket", (GuardedWebSocket,), {"send_timeout_s": settings.send_timeout_s})
    return http, ws


def uvicorn_config(app: Any, settings: ServiceSettings, **overrides: Any) -> uvicorn.Config:
    """The server's uvicorn configuration: guarded protocols, message size, connection cap."""
    http, ws = guarded_protocols(settings)
    options: dict[str, Any] = {
        "host": settings.host,
        "port": settings.port,
        "http": http,
        "ws": ws,
        "ws_max_size": 4 * settings.max_message_bytes,  # larger ones get a typed error, not a bare close
        "ws_per_message_deflate": False,  # compressing ~400-byte frames costs more CPU than it saves
        "ws_ping_interval": settings.ping_interval_s,
        "ws_ping_timeout": settings.ping_interval_s,
        "limit_concurrency": settings.max_connections,  # above it: 503 for HTTP, refused WebSocket handshakes
        "timeout_graceful_shutdown": max(1, round(0.15 * settings.drain_timeout_s)),
        **overrides,
    }
    return uvicorn.Config(app, **options)
