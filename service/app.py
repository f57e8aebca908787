"""FastAPI application: WebSocket streaming, REST for models and styles, health and metrics."""

from __future__ import annotations

import asyncio
import contextlib
from contextlib import asynccontextmanager

import torch
from threadpoolctl import threadpool_limits
from fastapi import Depends, FastAPI, HTTPException, Query, Request, Response, WebSocket
from fastapi.responses import JSONResponse, PlainTextResponse
from pydantic import BaseModel

from models.registry import load_models

from . import protocol as P
from .jobs import JobInfo, JobManager
from .limits import Limiter, Principal, unauthorized
from .runtime import Runtime
from .settings import ServiceSettings, get_service_settings
from .styles import ApiError, ErrorBody, StyleInfo, StyleStore, StyleUpload, UploadAccepted
from .stream import CLOSE_UNAUTHORIZED, Connection
from .routes_skeletons import router as skeletons_router
from .viewer import router as viewer_router


class ModelInfo(BaseModel):
    name: str
    styles: list[str]
    joints: list[str]
    controllable: bool = False  # a character controller: sessions may send `control` ticks instead of frames


class Health(BaseModel):
    status: str


async def _read_limited(request: Request, limit: int) -> bytes:
    """The request body, refusing (413) anything over `limit` bytes without reading it all."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise ApiError(413, "too_large", f"upload of {declared} bytes exceeds the limit of {limit}")
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            raise ApiError(413, "too_large", f"upload exceeds the limit of {limit} bytes")
    return bytes(body)


def create_app(settings: ServiceSettings | None = None, models: dict | None = None) -> FastAPI:
    settings = settings or get_service_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        torch.set_num_threads(settings.torch_threads)
        # numpy's OpenBLAS would otherwise spin extra threads on the model-step thread's small
        # matrix products, taking the core the event loop needs (measured: ~35% less server CPU
        # at 32 LTI sessions with one thread)
        threadpool_limits(settings.blas_threads, user_api="blas")
        runtime = Runtime(settings, models if models is not None else load_models(settings.weights_dir))
        styles = StyleStore(settings, runtime, JobManager())
        styles.load()  # persisted uploaded styles, before the batchers start
        styles.bind_loop(asyncio.get_running_loop())
        runtime.styles = styles
        await runtime.start()
        refresher = asyncio.get_running_loop().create_task(styles.refresh_loop()) if styles.shared else None
        app.state.runtime = runtime
        yield
        if refresher is not None:
            refresher.cancel()
        await styles.stop()
        await runtime.stop()
        app.state.runtime = None

    app = FastAPI(title="stylestream", version="0.1.0", lifespan=lifespan,
                  description="Online motion style transfer over WebSocket. Protocol: docs/protocol.md")
    app.state.runtime = None
    limiter = app.state.limiter = Limiter(settings)

    async def require_token(request: Request) -> Principal:
        """The caller (401 without a valid token), counted against its request rate (429).
        Async, so the limiter's counters are only ever touched on the event loop."""
        who = limiter.identify(request.headers.get("authorization"), request.query_params.get("token"),
                               request.client.host if request.client else None)
        if who is None:
            raise unauthorized()
        limiter.check_request(who)
        return who

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
        if request.app.state.runtime.draining:  # SIGTERM: load balancers stop sending new sessions
            response.status_code = 503
            return Health(status="draining")
        return Health(status="ready")

    @app.get("/metrics", response_class=PlainTextResponse)
    async def metrics(rt: Runtime = Depends(runtime)) -> Response:
        body, media_type = rt.metrics.render()
        return Response(body, media_type=media_type)

    @app.get("/v1/models", response_model=list[ModelInfo], dependencies=[Depends(require_token)],
             responses={s: {"model": ErrorBody} for s in (401, 429)})
    async def list_models(rt: Runtime = Depends(runtime)) -> list[ModelInfo]:
        await rt.styles.refresh()  # a styles folder shared with other replicas: what it holds now
        return [ModelInfo(name=n, styles=m.styles(), joints=list(m.skeleton.names),
                          controllable=getattr(m, "controllable", False)) for n, m in rt.models.items()]

    # ---- styles and jobs ----------------------------------------------------------
    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse({"code": exc.code, "message": exc.message}, status_code=exc.status,
                            headers=getattr(exc, "headers", None))

    errors = {s: {"model": ErrorBody} for s in (401, 404, 409, 413, 422, 429)}

    @app.get("/v1/styles", response_model=list[StyleInfo], dependencies=[Depends(require_token)], responses=errors)
    async def list_styles(model: str | None = None, rt: Runtime = Depends(runtime)) -> list[StyleInfo]:
        await rt.styles.refresh()
        return rt.styles.list(model)

    @app.get("/v1/styles/{style_id}", response_model=StyleInfo, dependencies=[Depends(require_token)], responses=errors)
    async def get_style(style_id: str, rt: Runtime = Depends(runtime)) -> StyleInfo:
        await rt.styles.refresh()
        return rt.styles.get(style_id)

    @app.delete("/v1/styles/{style_id}", status_code=204, dependencies=[Depends(require_token)], responses=errors)
    async def delete_style(style_id: str, rt: Runtime = Depends(runtime)) -> Response:
        await rt.styles.refresh()  # the style may have come from another replica since the last look
        await rt.styles.delete(style_id)
        return Response(status_code=204)

    upload_body = {"requestBody": {"required": True, "content": {
        "application/json": {"schema": StyleUpload.model_json_schema()},
        "multipart/form-data": {"schema": {"type": "object", "required": ["file", "name"], "properties": {
            "file": {"type": "string", "format": "binary", "description": "BVH clip (Bandai Namco or CMU skeleton)"},
            "name": {"type": "string"}, "model": {"type": "string", "default": "lti"},
            "fine_tune": {"type": "boolean", "default": False}}}}}}}

    @app.post("/v1/styles", response_model=UploadAccepted, status_code=202, dependencies=[Depends(require_token)],
              responses=errors, openapi_extra=upload_body)
    async def upload_style(request: Request, response: Response, fine_tune: bool | None = Query(default=None),
                           name: str | None = Query(default=None), model: str | None = Query(default=None),
                           rt: Runtime = Depends(runtime), who: Principal = Depends(require_token)) -> UploadAccepted:
        """Upload a clip as a new style: multipart BVH (`file`) or JSON frames. LTI styles need
        `fine_tune=true`, which starts the identification job (`GET /v1/jobs/{id}`), answered 202;
        an LPN-FiLM style is the clip's FiLM embedding, ready at once, answered 201, with
        `fine_tune=true` also a job that fine-tunes the FiLM generator on the clip and then
        swaps in the tuned FiLM vector."""
        body = await _read_limited(request, who.limits.upload_max_bytes)
        ctype = request.headers.get("content-type", "")
        upload, bvh_text, fields = None, None, {}
        if ctype.startswith("multipart/form-data"):
            async def receive() -> dict:
                return {"type": "http.request", "body": body, "more_body": False}
            try:
                form = await Request(request.scope, receive).form()
            except Exception as exc:  # noqa: BLE001
                raise ApiError(422, "bad_request", f"unreadable multipart body: {exc}") from None
            file = form.get("file")
            if file is None or isinstance(file, str):
                raise ApiError(422, "bad_request", "multipart upload needs a 'file' part with the BVH clip")
            try:
                bvh_text = (await file.read()).decode("utf-8")
            except UnicodeDecodeError:
                raise ApiError(422, "bad_bvh", "the BVH file is not UTF-8 text") from None
            fields = {k: v for k, v in form.items() if isinstance(v, str)}
            fine = fields.get("fine_tune", "false").lower() in ("1", "true", "yes", "on")
        elif ctype.startswith("application/json"):
            try:
                upload = StyleUpload.model_validate_json(body)
            except ValueError as exc:
                raise ApiError(422, "bad_request", f"invalid JSON upload: {str(exc)[:500]}") from None
            fields = {"name": upload.name, "model": upload.model}
            fine = upload.fine_tune
        else:
            raise ApiError(415, "unsupported_media_type", "send multipart/form-data (file=BVH) or application/json frames")
        fine = fine if fine_tune is None else fine_tune
        style_name = name or fields.get("name") or ""
        model_name = model or fields.get("model") or "lti"
        accepted = await rt.styles.upload(upload, bvh_text, style_name, model_name, fine)
        if accepted.style.status == "ready":  # a clip embedding (LPN-FiLM): the style exists already, job or not
            response.status_code = 201
        return accepted

    @app.get("/v1/jobs/{job_id}", response_model=JobInfo, dependencies=[Depends(require_token)], responses=errors)
    async def get_job(job_id: str, rt: Runtime = Depends(runtime)) -> JobInfo:
        job = await rt.styles.job(job_id)  # this replica's, or one stored with its style in the folder
        if job is None:
            raise ApiError(404, "unknown_job", f"no job {job_id!r}")
        return job

    @app.websocket("/v1/stream")
    async def stream(ws: WebSocket) -> None:
        await ws.accept()
        who = limiter.identify(ws.headers.get("authorization"), ws.query_params.get("token"),
                               ws.client.host if ws.client else None)
        if who is None:
            await ws.close(CLOSE_UNAUTHORIZED, "missing or invalid API token")
            return
        connection = Connection(ws, ws.app.state.runtime)
        try:
            limiter.open_session(who)
        except P.ProtocolError as err:  # the token's session cap: typed error, then 1013,
            with contextlib.suppress(TimeoutError):  # answering the client's start, as other refusals do
                await asyncio.wait_for(ws.receive(), timeout=min(5.0, settings.idle_timeout_s))
            await connection.send_error(err)
            await connection.close(err.close_code, err.message)
            return
        try:
            await connection.run()
        finally:
            limiter.session_closed(who)

    app.include_router(viewer_router)
    app.include_router(skeletons_router, dependencies=[Depends(require_token)])
    return app
