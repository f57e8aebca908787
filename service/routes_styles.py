"""`/v1/styles` and `/v1/jobs`: list, get, delete and upload styles, and follow fine-tuning jobs.

The routes read the request (an upload is multipart BVH or JSON frames, size-capped per token)
and hand the rest to the style store (`styles.py`); refusals are `ApiError`s."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Query, Request, Response

from .api import ApiError, StyleInfo, StyleUpload, UploadAccepted, error_responses
from .background import in_background
from .clip_worker import Body, Upload
from .deps import get_runtime, require_token
from .jobs import JobInfo
from .limits import Principal
from .memory import LARGE_REQUEST_BYTES, release_freed_memory
from .runtime import Runtime

router = APIRouter()
UNKNOWN_STYLE = {404: "`unknown_style`: no style with this id."}
UPLOAD_NOTES = {
    409: "`style_exists`: the model has a style of this name; `training_data_unavailable`: this server "
    "lacks the data fine-tuning needs.",
    413: "`too_large`: the body is over the token's upload limit; `clip_too_large`: decoding the clip "
    "ran out of its memory budget.",
    422: "`bad_name`, `unknown_model`, `uploads_unsupported`, `fine_tune_required`, `bad_bvh`, "
    "`unsupported_skeleton`, `bad_frames`, `bad_skeleton`, `non_finite`, `bad_frame_rate`, `bad_length`, "
    "`clip_too_slow`, `bad_clip`, `bad_request`.",
    503: "`server_busy`: the clip's decoding was given no CPU in time (`upload_decode_wall_s`); Retry-After "
    "says when to try again.",
}
UPLOAD_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": StyleUpload.model_json_schema()},
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file", "name"],
                    "properties": {
                        "file": {
                            "type": "string",
                            "format": "binary",
                            "description": "BVH clip (Bandai Namco or CMU skeleton)",
                        },
                        "name": {"type": "string"},
                        "model": {"type": "string", "default": "lti"},
                        "fine_tune": {"type": "boolean", "default": False},
                    },
                }
            },
        },
    }
}


async def _read_limited(request: Request, limit: int) -> Body:
    """The request body, refusing (413) anything over `limit` bytes without reading it all, kept
    as the chunks it came in: the child that decodes it joins them. Growing one buffer instead
    copied it whole at every reallocation, up to 16 MB in one go: ~5 ms during which no stream
    was served, several times per large upload (issue #16)."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise ApiError(413, "too_large", f"upload of {declared} bytes exceeds the limit of {limit}")
    body: Body = []
    size = 0
    async for chunk in request.stream():
        if chunk:
            body.append(chunk)
            size += len(chunk)
        if size > limit:
            raise ApiError(413, "too_large", f"upload exceeds the limit of {limit} bytes")
    return body


@router.get(
    "/v1/styles",
    response_model=list[StyleInfo],
    dependencies=[Depends(require_token)],
    summary="Every style: trained and uploaded, ready or training",
    tags=["styles"],
    responses=error_responses(401, 429, 503),
)
async def list_styles(
    model: str | None = None, rt: Runtime = Depends(get_runtime), who: Principal = Depends(require_token)
) -> list[StyleInfo]:
    await rt.styles.refresh()
    return rt.styles.list(model, who)


@router.get(
    "/v1/styles/{style_id}",
    response_model=StyleInfo,
    dependencies=[Depends(require_token)],
    summary="One style",
    tags=["styles"],
    responses=error_responses(401, 404, 429, 503, notes=UNKNOWN_STYLE),
)
async def get_style(
    style_id: str, rt: Runtime = Depends(get_runtime), who: Principal = Depends(require_token)
) -> StyleInfo:
    await rt.styles.refresh()
    return rt.styles.get(style_id, who)


@router.delete(
    "/v1/styles/{style_id}",
    status_code=204,
    dependencies=[Depends(require_token)],
    summary="Delete an uploaded style",
    tags=["styles"],
    responses=error_responses(
        401, 404, 409, 429, 503, notes={**UNKNOWN_STYLE, 409: "`trained_style`: trained styles cannot be deleted."}
    ),
)
async def delete_style(
    style_id: str, rt: Runtime = Depends(get_runtime), who: Principal = Depends(require_token)
) -> Response:
    await rt.styles.refresh()  # the style may have come from another replica since the last look
    await rt.styles.delete(style_id, who)
    return Response(status_code=204)


@router.post(
    "/v1/styles",
    response_model=UploadAccepted,
    status_code=202,
    dependencies=[Depends(require_token)],
    summary="Upload a clip as a new style",
    tags=["styles"],
    response_description="Accepted: the style is `training`; follow `job` (`GET /v1/jobs/{id}`).",
    responses={
        201: {
            "model": UploadAccepted,
            "description": "Created: the style is `ready` (LPN-FiLM); `job` if fine-tuning.",
        },
        **error_responses(401, 409, 413, 415, 422, 429, 503, 507, notes=UPLOAD_NOTES),
    },
    openapi_extra=UPLOAD_BODY,
)
async def upload_style(
    request: Request,
    response: Response,
    fine_tune: bool | None = Query(default=None),
    name: str | None = Query(default=None),
    model: str | None = Query(default=None),
    rt: Runtime = Depends(get_runtime),
    who: Principal = Depends(require_token),
) -> UploadAccepted:
    """Upload a clip as a new style: multipart BVH (`file`) or JSON frames. LTI styles need
    `fine_tune=true`, which starts the identification job (`GET /v1/jobs/{id}`), answered 202;
    an LPN-FiLM style is the clip's FiLM embedding, ready at once, answered 201, with
    `fine_tune=true` also a job that fine-tunes the FiLM generator on the clip and then
    swaps in the tuned FiLM vector. A Style-ERD style is ready at once too (the nearest trained
    branch, stages fitted from the clip); its job fits a residual branch of its own."""
    body = await _read_limited(request, who.limits.upload_max_bytes)
    ctype = request.headers.get("content-type", "")
    kind: Upload
    if ctype.startswith("multipart/form-data"):
        kind = "multipart"  # parsed in the decoding child, with the clip: a large form never holds the event loop
    elif ctype.startswith("application/json"):
        kind = "json"  # its fields are read with its frames, in the decoding child
    else:
        raise ApiError(415, "unsupported_media_type", "send multipart/form-data (file=BVH) or application/json frames")
    overrides = {"name": name, "model": model, "fine_tune": fine_tune}
    fields = {k: v for k, v in overrides.items() if v is not None}
    large = sum(map(len, body)) >= LARGE_REQUEST_BYTES
    try:
        accepted = await rt.styles.upload(kind, body, fields, who, ctype)
    finally:
        del body
        if large:  # its copies are freed by now: hand their pages back (`service.memory`)
            await in_background(release_freed_memory)
    if accepted.style.status == "ready":  # made from the clip at once (LPN-FiLM): the style exists already, job or not
        response.status_code = 201
    return accepted


@router.get(
    "/v1/jobs/{job_id}",
    response_model=JobInfo,
    dependencies=[Depends(require_token)],
    summary="A fine-tuning job: status and progress",
    tags=["styles"],
    responses=error_responses(401, 404, 429, 503, notes={404: "`unknown_job`: no job with this id."}),
)
async def get_job(job_id: str, rt: Runtime = Depends(get_runtime)) -> JobInfo:
    job = await rt.styles.job(job_id)  # this replica's, or one stored with its style in the folder
    if job is None:
        raise ApiError(404, "unknown_job", f"no job {job_id!r}")
    return job
