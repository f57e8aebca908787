"""`WS /v1/stream`: authenticate, take one of the caller's sessions, and run the connection
(`stream.Connection`; the protocol is docs/protocol.md)."""

from __future__ import annotations

import asyncio
import contextlib
import math

from fastapi import APIRouter, WebSocket
from fastapi.responses import JSONResponse

from . import protocol as P
from .api import ApiError
from .deps import get_limiter
from .limits import CLOSE_TRY_AGAIN_LATER
from .runtime import Runtime
from .stream import CLOSE_UNAUTHORIZED, Connection, serve

router = APIRouter()


def rate_limited_response(wait: float) -> JSONResponse:
    """HTTP 429 to a WebSocket handshake from a caller cooling down after a flood."""
    message = f"a connection of this caller was closed for flooding; new streams are refused for {wait:.1f} s more"
    return JSONResponse(
        {"code": "rate_limited", "message": message}, 429, {"Retry-After": str(max(1, math.ceil(wait)))}
    )


@router.websocket("/v1/stream")
async def stream(ws: WebSocket) -> None:
    limiter = get_limiter(ws)
    try:
        who = limiter.identify(
            ws.headers.get("authorization"), ws.query_params.get("token"), ws.client.host if ws.client else None
        )
    except ApiError as err:  # too many failed authentications from this address
        await ws.accept()
        await ws.close(CLOSE_TRY_AGAIN_LATER, P.close_reason(err.message))
        return
    if who is None:
        await ws.accept()
        await ws.close(CLOSE_UNAUTHORIZED, "missing or invalid API token")
        return
    if wait := limiter.cooldown_left(who):  # it flooded and reconnects: refused before the upgrade, cheaply
        await ws.send_denial_response(rate_limited_response(wait))
        return
    await ws.accept()
    runtime: Runtime = ws.app.state.runtime  # set before the server takes connections (the app's lifespan)
    connection = Connection(ws, runtime, who)
    try:
        limiter.open_session(who)
    except P.ProtocolError as err:  # the token's session cap: typed error, then 1013,
        with contextlib.suppress(TimeoutError):  # answering the client's start, as other refusals do
            await asyncio.wait_for(ws.receive(), timeout=min(5.0, runtime.settings.idle_timeout_s))
        await connection.send_error(err)
        await connection.close(err.close_code, err.message)
        return
    try:
        await serve(ws, runtime, who)
    finally:
        limiter.session_closed(who)
