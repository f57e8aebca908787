"""`/healthz` (the process answers), `/readyz` (it takes sessions: 503 while loading, draining or
full) and `/metrics` (Prometheus text); no token, for probes and scrapers. The two probes are
answered whatever the connection count (`transport.GuardedHttp`): a server at `max_connections`
is alive, and says it is full."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response

from .api import Health, error_responses
from .deps import get_runtime
from .runtime import Runtime
from .transport import CONNECTIONS

router = APIRouter()


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers", tags=["health"])
async def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Health,
    summary="Readiness: the server takes new sessions",
    tags=["health"],
    responses={
        503: {
            "model": Health,
            "description": "Not taking sessions: `status` is `loading`, `draining` or `full` (every session "
            "or connection taken).",
        }
    },
)
async def readyz(request: Request, response: Response) -> Health:
    runtime: Runtime | None = request.app.state.runtime
    if runtime is None:
        response.status_code = 503
        return Health(status="loading")
    if runtime.draining:  # SIGTERM: load balancers stop sending new sessions
        response.status_code = 503
        return Health(status="draining")
    connections, most = request.scope.get(CONNECTIONS, (0, None))
    if runtime.full() or (most is not None and connections >= most):  # alive, but send new work elsewhere
        response.status_code = 503
        return Health(status="full")
    return Health(status="ready")


@router.get(
    "/metrics",
    response_class=Response,  # PlainTextResponse would describe the 503's JSON body as text/plain
    summary="Prometheus metrics (text exposition format)",
    tags=["health"],
    responses={
        200: {"description": "Prometheus text", "content": {"text/plain": {"schema": {"type": "string"}}}},
        **error_responses(503),
    },
)
async def metrics(rt: Runtime = Depends(get_runtime)) -> Response:
    body, media_type = rt.metrics.render()
    return Response(body, media_type=media_type)
