"""FastAPI application: WebSocket streaming, REST for models and styles, health and metrics.

`create_app` builds the app from its routers (`routes_*.py`, `viewer.py`) and, in its lifespan,
the server's parts in the order they depend on each other: the models (each with a style set of
its own) and, unless `core_pipelines` is off, each one's published core alone
(`service.pipelines`; loaded at start: ~0.3 s and ~35 MB beside the shipped models, too little
to defer), the model-step worker thread, the style store (which loads the persisted uploaded
styles into the models), and the runtime that streams them.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import torch
from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from threadpoolctl import threadpool_limits

from models.interface import StreamingModel, own_style_set
from models.registry import load_models

from .api import ApiError, error_responses, invalid_request
from .batcher import ModelThread
from .deps import require_token
from .jobs import JobManager
from .limits import Limiter
from .pipelines import core_pipelines
from .routes_docs import install_docs
from .routes_health import router as health_router
from .routes_models import router as models_router
from .routes_skeletons import router as skeletons_router
from .routes_stream import router as stream_router
from .routes_styles import router as styles_router
from .runtime import Runtime
from .settings import ServiceSettings, get_service_settings
from .styles import StyleStore
from .viewer import router as viewer_router


def create_app(
    settings: ServiceSettings | None = None,
    models: dict[str, StreamingModel] | None = None,
    core_models: dict[str, StreamingModel] | None = None,
) -> FastAPI:
    """The app; `models` (tests): serve these instead of the committed ones, and then only the
    cores in `core_models` (`load_models(..., core_only=True)`), none unless given."""
    settings = settings or get_service_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        torch.set_num_threads(settings.torch_threads)
        # numpy's OpenBLAS would otherwise spin extra threads on the model-step thread's small
        # matrix products, taking the core the event loop needs (measured: ~35% less server CPU
        # at 32 LTI sessions with one thread)
        threadpool_limits(settings.blas_threads, user_api="blas")
        given = (
            models
            if models is not None
            else load_models(
                settings.weights_dir, novelty=settings.unseen_fade, calibration=settings.posture_calibration
            )
        )
        cores: dict[str, StreamingModel] = {}
        if settings.core_pipelines:
            cores = (core_models or {}) if models is not None else load_models(settings.weights_dir, core_only=True)
        own = {name: own_style_set(model) for name, model in given.items()}
        model_thread = ModelThread()
        styles = StyleStore(settings, own, model_thread, JobManager())
        styles.load()  # persisted uploaded styles, before the batchers start
        styles.bind_loop(asyncio.get_running_loop())
        cores = {name: core for name, core in cores.items() if name in own}  # a core beside its full pipeline
        runtime = Runtime(settings, own, model_thread, styles, core_pipelines(cores))
        await runtime.start()
        refresher = asyncio.get_running_loop().create_task(styles.refresh_loop()) if styles.shared else None
        app.state.runtime = runtime
        yield
        if refresher is not None:
            refresher.cancel()
        await styles.stop()
        await runtime.stop()
        app.state.runtime = None

    app = FastAPI(
        title="stylestream",
        version="0.1.0",
        lifespan=lifespan,
        docs_url=None,  # served by routes_docs, from this server instead of a CDN
        redoc_url=None,
    )
    app.state.runtime = None
    app.state.limiter = Limiter(settings)

    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError) -> JSONResponse:
        """An `ApiError` as its status and `{"code", "message"}`, with its headers."""
        return JSONResponse({"code": exc.code, "message": exc.message}, status_code=exc.status, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        """A request that does not match its schema: 422 in the same shape, `bad_request`."""
        return JSONResponse(invalid_request(exc.errors()), status_code=422)

    for router in (health_router, models_router, styles_router, stream_router, viewer_router):
        app.include_router(router)
    app.include_router(skeletons_router, dependencies=[Depends(require_token)], responses=error_responses(401, 429))
    install_docs(app)
    return app
