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
`send_timeout_s`. A client closed for flooding (4429) gets a lingering close, as nginx's
`lingering_close` does for HTTP: the close frame, then end-of-stream, while what the client still
sends is read and dropped unparsed (parsing a flood's frames after the close cost the event loop)
until it closes too, or `send_timeout_s` or FLOOD_LINGER_MAX_BYTES runs out. Not reading instead
left a client that was blocked writing its flood unable to take the close frame in: its socket
was reset with the frame unread and it saw 1006, not 4429 (the websockets sync client holds its
connection lock while a send blocks, so its reader cannot parse the close meanwhile).

`GuardedWebSocket` also offers the app a direct frame path, as the ASGI extension
DIRECT_FRAMES in the connection's scope: the app may set `binary_sink`, which is offered each
binary message as the protocol parses it, before it is queued for the app's `receive`, and
may answer with `write_binary` from any callback. A frame taken that way costs no task wake-up,
no ASGI message dict and no pause/resume of the socket's reads (issue 17; 64 spread LTI sessions,
alternating: 89-111 us of server CPU per frame this way, 115-126 us through ASGI receive/send).
The sink declines whatever it cannot finish at once; that message then takes the ASGI path, in
order.
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Callable
from typing import Any

import httptools
import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.utils import ClientDisconnected
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.exceptions import InvalidState
from websockets.http11 import Request

from .limits import CLOSE_FLOODING
from .settings import ServiceSettings

# What a client closed for flooding may still send, read and dropped, before it is reset. The test
# suite's flood script (sync websockets client, json.dumps per frame) closed within 26 ms having sent
# at most 0.7 MB more, in ten runs beside four busy processes. hostile_bench's flooder, which sends
# ready-made frames in a tight loop, never lets its reader thread in and reaches the cap in ~0.3 s
FLOOD_LINGER_MAX_BYTES = 64 << 20
# Each connection's header deadline is header_timeout_s times 1 .. 1 + this (uniform): connections
# opened together (2,000 half-open ones in a burst) are then not all aborted in one pass of the
# event loop, which held the healthy sessions' frames (hostile_bench half-open phase, p99 / quiet
# 1.07-4.91 in three runs at one deadline, 0.81-1.14 spread)
HEADER_DEADLINE_SPREAD = 0.5
# Probes are never refused by the connection cap (`GuardedHttp.on_headers_complete`); their scope
# carries (open connections, max_connections) under CONNECTIONS for the readiness answer
PROBE_PATHS = (b"/healthz", b"/readyz")
CONNECTIONS = "stylestream.connections"
# The ASGI scope extension under which `GuardedWebSocket` offers its direct frame path (module doc)
DIRECT_FRAMES = "stylestream.direct_frames"


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
        limit = self.limit_concurrency
        if limit is None or httptools.parse_url(self.url).path not in PROBE_PATHS:
            super().on_headers_complete()
            return
        # a probe: answered whatever the connection count (uvicorn's limit answers 503 before the
        # app: at max_connections an orchestrator would restart a healthy, merely full, server),
        # and told that count, so readiness can say the server is full
        self.scope[CONNECTIONS] = (len(self.connections), limit)  # type: ignore[literal-required]
        self.limit_concurrency = None
        try:
            super().on_headers_complete()
        finally:
            self.limit_concurrency = limit

    def connection_lost(self, exc: Exception | None) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        super().connection_lost(exc)


class GuardedWebSocket(WebSocketsSansIOProtocol):
    send_timeout_s = 10.0
    direct_frames = True  # offer the direct frame path (module doc) to the app
    linger_bytes_left: int | None = None  # set once closed for flooding: what it may still send
    # set by the app: takes a binary message now (True) or declines it (False: it is queued for `receive`)
    binary_sink: Callable[[bytes], bool] | None = None

    def handle_connect(self, event: Request) -> None:
        super().handle_connect(event)
        if self.direct_frames and self.response.status_code == 101:  # the app's task has the scope, not yet run
            self.scope["extensions"][DIRECT_FRAMES] = self  # type: ignore[assignment]

    def send_receive_event_to_app(self) -> None:
        """A whole message: offered to `binary_sink` first when it is binary and nothing is
        queued ahead of it for the app (the app's messages stay in order)."""
        sink = self.binary_sink
        if sink is not None and self.curr_msg_data_type == "bytes" and not self.close_sent and self.queue.empty():
            data = self.frames[0] if len(self.frames) == 1 else b"".join(self.frames)
            if sink(data):
                self.frames = []
                return
        super().send_receive_event_to_app()

    def write_binary(self, data: bytes) -> bool:
        """Send a binary message now, from a plain callback; False (nothing sent) when it could
        not go without waiting: the peer is not reading (the transport is paused), or the
        connection is closing. The caller then sends it the awaiting way, which waits or fails."""
        if not self.handshake_complete or self.close_sent or self.disconnected or not self.writable.is_set():
            return False
        try:
            self.conn.send_binary(data)
        except InvalidState:
            return False
        self.transport.write(b"".join(self.conn.data_to_send()))
        return True

    def data_received(self, data: bytes) -> None:
        if self.linger_bytes_left is None:
            super().data_received(data)
            return
        self.linger_bytes_left -= len(data)  # lingering after a flood close: dropped unparsed
        if self.linger_bytes_left < 0:
            self.transport.abort()

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
            if message.get("code") == CLOSE_FLOODING and not self.transport.is_closing():
                self._linger()
            self.close_timer = self.loop.call_later(self.send_timeout_s, self.transport.abort)

    def _linger(self) -> None:
        """Closed for flooding: end our side after the close frame and drop what it still sends,
        so a client blocked writing its flood gets unblocked and reads the close (module doc)."""
        self.stop_keepalive()
        self.linger_bytes_left = FLOOD_LINGER_MAX_BYTES
        if self.read_paused:  # uvicorn resumes reads on close already; said here, it is relied on
            self.read_paused = False
            self.transport.resume_reading()
        if self.transport.can_write_eof():  # not over TLS: there the client's own close, or the deadline, ends it
            self.transport.write_eof()  # after the buffered close frame: the client's reader sees it, then EOF

    def connection_lost(self, exc: Exception | None) -> None:
        self.binary_sink = None  # the app's receive gets its disconnect; nothing more goes to the sink
        super().connection_lost(exc)

    def keepalive_timeout(self) -> None:
        super().keepalive_timeout()  # it closes, which flushes first: a peer that does not read is aborted instead
        self.transport.abort()


def guarded_protocols(settings: ServiceSettings) -> tuple[type[GuardedHttp], type[GuardedWebSocket]]:
    """The two protocol classes with this server's deadlines (uvicorn instantiates them itself)."""
    http = type("GuardedHttp", (GuardedHttp,), {"header_timeout_s": settings.header_timeout_s})
    ws = type(
        "GuardedWebSocket",
        (GuardedWebSocket,),
        {"send_timeout_s": settings.send_timeout_s, "direct_frames": settings.direct_frames},
    )
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
