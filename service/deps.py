"""What the routes take from the app: its runtime (503 while it starts) and the caller (401, 429)."""

from __future__ import annotations

from fastapi import Request
from starlette.requests import HTTPConnection

from .api import ApiError
from .limits import Limiter, Principal, unauthorized
from .runtime import Runtime


def get_runtime(request: Request) -> Runtime:
    runtime: Runtime | None = request.app.state.runtime
    if runtime is None:
        raise ApiError(503, "starting_up", "the server is starting; try again shortly", {"Retry-After": "1"})
    return runtime


def get_limiter(connection: HTTPConnection) -> Limiter:
    limiter: Limiter = connection.app.state.limiter
    return limiter


async def require_token(request: Request) -> Principal:
    """The caller (401 without a valid token), counted against its request rate (429).
    Async, so the limiter's counters are only ever touched on the event loop."""
    limiter = get_limiter(request)
    who = limiter.identify(
        request.headers.get("authorization"),
        request.query_params.get("token"),
        request.client.host if request.client else None,
    )
    if who is None:
        raise unauthorized()
    limiter.check_request(who)
    return who
