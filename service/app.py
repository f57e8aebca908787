"""FastAPI application: health, readiness and model listing.

Streaming sessions (WS /v1/stream), cross-session batching and style upload come with the
service issue; this app already loads every committed model through `models.registry`.
"""

from __future__ import annotations

from contextlib import asynccontextmanager

import torch
from fastapi import FastAPI, Response
from pydantic import BaseModel

from models.registry import load_models

from .settings import ServiceSettings, get_service_settings


class ModelInfo(BaseModel):
    name: str
    styles: list[str]


class Health(BaseModel):
    status: str


def create_app(settings: ServiceSettings | None = None) -> FastAPI:
    settings = settings or get_service_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        torch.set_num_threads(settings.torch_threads)
        app.state.models = load_models(settings.weights_dir)
        app.state.ready = True
        yield
        app.state.ready = False

    app = FastAPI(title="stylestream", version="0.1.0", lifespan=lifespan)
    app.state.ready = False
    app.state.models = {}

    @app.get("/healthz", response_model=Health)
    async def healthz() -> Health:
        return Health(status="ok")

    @app.get("/readyz", response_model=Health)
    async def readyz(response: Response) -> Health:
        if not app.state.ready:
            response.status_code = 503
            return Health(status="loading")
        return Health(status="ready")

    @app.get("/v1/models", response_model=list[ModelInfo])
    async def list_models() -> list[ModelInfo]:
        return [ModelInfo(name=name, styles=model.styles()) for name, model in app.state.models.items()]

    return app
