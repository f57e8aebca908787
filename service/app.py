"""FastAPI application: WebSocket streaming, REST for models and styles, health and metrics."""

from __future__ import annotations

import secrets
from contextlib import asynccontextmanager

import torch
from fastapi import Depends, FastAPI, HTTPException, Request, Response, WebSocket
from fastapi.responses import PlainTextResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel

from models.registry import load_models

from .runtime import Runtime
from .settings import ServiceSettings, get_service_settings
from .stream import CLOSE_UNAUTHORIZED, Connection


class ModelInfo(BaseModel):
    name: str
    styles: list[str]
    joints: list[str]


class Health(BaseModel):
    status: str


def _token_ok(settings: ServiceSettings, header: str | None, query: str | None) -> bool:
    if not settings.api_tokens:
        return True
    given = query or (header[7:] if header and header.lower().startswith("bearer ") else None)
    return given is not None and any(secrets.compare_digest(given, t) for t in settings.api_tokens)


def create_app(settings: ServiceSettings | None = None, models: dict | None = None) -> FastAPI:
    settings = settings or get_service_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        torch.set_num_threads(settings.torch_threads)
        runtime = Runtime(settings, models if models is not None else load_models(settings.weights_dir))
        await runtime.start()
        app.state.runtime = runtime
        yield
        await runtime.stop()
        app.state.runtime = None

    app = FastAPI(title="stylestream", version="0.1.0", lifespan=lifespan,
                  description="Online motion style transfer over WebSocket. Protocol: docs/protocol.md")
    app.state.runtime = None

    def require_token(request: Request) -> None:
        if not _token_ok(settings, request.headers.get("authorization"), request.query_params.get("token")):
            raise HTTPException(401, "missing or invalid API token", headers={"WWW-Authenticate": "Bearer"})

    def runtime(request: Request) -> Runtime:
        if request.app.state.runtime is None:
            raise HTTPException(503, "starting up")
        return request.app.state.runtime

    @app.get("/healthz", response_model=Health)
    async def healthz() -> Health:
        return Health(status="ok")

    @app.get("/readyz", response_model=Health)
    async def readyz(request: Request, response: Response) -> Health:
        if request.app.state.runtime is None:
            response.status_code = 503
            return Health(status="loading")
        return Health(status="ready")

    @app.get("/metrics", response_class=PlainTextResponse)
    async def metrics(rt: Runtime = Depends(runtime)) -> Response:
        return Response(generate_latest(rt.metrics.registry), media_type=CONTENT_TYPE_LATEST)

    @app.get("/v1/models", response_model=list[ModelInfo], dependencies=[Depends(require_token)])
    async def list_models(rt: Runtime = Depends(runtime)) -> list[ModelInfo]:
        return [ModelInfo(name=n, styles=m.styles(), joints=list(m.skeleton.names)) for n, m in rt.models.items()]

    @app.websocket("/v1/stream")
    async def stream(ws: WebSocket) -> None:
        await ws.accept()
        if not _token_ok(settings, ws.headers.get("authorization"), ws.query_params.get("token")):
            await ws.close(CLOSE_UNAUTHORIZED, "missing or invalid API token")
            return
        rt = ws.app.state.runtime
        await Connection(ws, rt).run()

    return app
