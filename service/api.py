"""The REST API's bodies (pydantic schemas, so the OpenAPI document describes them) and its error.

Every refusal is an `ApiError`: the app answers it with its status and `{"code", "message"}`
(`ErrorBody`), plus headers where it carries any (Retry-After, WWW-Authenticate). It lives here,
apart from what raises it (the style store, the clip decoding, the limiter), so none of them
imports another for it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

from pydantic import BaseModel, Field

from .jobs import JobInfo


class ApiError(Exception):
    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.headers = status, code, message, headers


class ErrorBody(BaseModel):
    code: str
    message: str


# What each refusal status means on every route that gives it, with the `code`s it carries; a
# route adds its own codes (`error_responses(..., notes=...)`)
ERROR_MEANINGS: dict[int, str] = {
    401: "No valid API token (`Authorization: Bearer <token>` or `?token=`): `unauthorized`.",
    404: "Not found.",
    409: "Conflicts with what the server holds.",
    413: "Too large.",
    415: "Unsupported content type: `unsupported_media_type`.",
    422: "The request is well formed HTTP but its content is refused; `code` says why "
    "(`bad_request` for a parameter or body that does not match its schema).",
    429: "Over the token's request rate: `rate_limited`; Retry-After says when the next request passes.",
    503: "The server is starting: `starting_up`.",
    507: "The server could not store it: `storage_full`.",
}
ERROR_HEADERS: dict[int, dict[str, Any]] = {
    401: {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}},
    429: {"Retry-After": {"description": "seconds until a request passes", "schema": {"type": "integer"}}},
    503: {"Retry-After": {"description": "seconds to wait before trying again", "schema": {"type": "integer"}}},
}


def error_responses(*statuses: int, notes: dict[int, str] | None = None) -> dict[int | str, dict[str, Any]]:
    """The `responses` of a route that may answer these statuses with an `ErrorBody`: each with
    its general meaning (`ERROR_MEANINGS`) and the route's own `notes` (the codes it gives), so
    the OpenAPI document lists every refusal a client must handle."""
    out: dict[int | str, dict[str, Any]] = {}
    for status in statuses:
        text = " ".join(t for t in (ERROR_MEANINGS.get(status, ""), (notes or {}).get(status, "")) if t)
        out[status] = {"model": ErrorBody, "description": text or "Error."}
        if status in ERROR_HEADERS:
            out[status]["headers"] = ERROR_HEADERS[status]
    return out


def invalid_request(errors: Sequence[Any]) -> dict[str, str]:
    """A request that does not match its schema (FastAPI's validation errors) as an `ErrorBody`,
    `bad_request`, naming the first few fields and what is wrong with each: one error shape for
    every refusal, as clients (the SDK) read it."""
    parts = [f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg', 'invalid')}" for e in errors[:5]]
    return {"code": "bad_request", "message": "; ".join(parts)[:1000] or "invalid request"}


class Health(BaseModel):
    status: str


class ModelInfo(BaseModel):
    name: str
    styles: list[str]
    joints: list[str]
    controllable: bool = False  # a character controller: sessions may send `control` ticks instead of frames
    pipelines: list[Literal["full", "core"]] = Field(
        default=["full"],
        description="What a session may ask for in `pipeline`: `full` (the shipped pipeline) and, where "
        "served, `core` (the published method alone: its built-in styles, no fitted stages)",
    )


class StyleInfo(BaseModel):
    id: str = Field(description="'<model>.<name>'")
    name: str
    model: str
    kind: Literal["trained", "uploaded"]
    status: Literal["ready", "training", "failed"]
    created: float | None = Field(default=None, description="Unix time (trained: weights file time).")
    job_id: str | None = None
    message: str | None = None
    frames: int | None = Field(default=None, description="Uploaded clip length at 30 fps.")
    source: Literal["bvh", "json"] | None = None
    skeleton: str | None = Field(
        default=None,
        description="Rig of the uploaded clip (bandai-namco, a preset such as cmu or mixamo, or humanoid).",
    )
    owner: str = Field(
        default="",
        description="The uploading tenant: a one-way id of its API token (empty: uploaded without tokens, everyone's).",
    )
    fine_tune: dict | None = Field(
        default=None,
        description="Fine-tuning summary: seconds, and for LTI neutral clips and "
        "held-out metrics, for LPN-FiLM the loss on the clip's held-back frames before and after.",
    )


class UploadFrames(BaseModel):
    root: list[list[float]] = Field(description="(F, 3) Hips translation, cm")
    rotations: list[list[list[float]]] = Field(
        description="(F, 22, 4) local rotations, quaternions xyzw, BN joint order"
    )


class StyleUpload(BaseModel):
    name: str
    model: str = "lti"
    frames: UploadFrames
    fps: float = Field(default=30.0, gt=0, le=240)
    fine_tune: bool = False


class UploadAccepted(BaseModel):
    style: StyleInfo
    job: JobInfo | None = None
