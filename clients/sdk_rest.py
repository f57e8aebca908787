"""The REST calls (models, styles, jobs) once, for the sync and asyncio clients (see `sdk_io`)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .sdk_io import HttpReply, Request, Sleep, Steps
from .sdk_types import (
    AddedStyle,
    JobFailed,
    JobInfo,
    JobTimeout,
    ModelInfo,
    ServerError,
    StyleInfo,
    Upload,
    from_json,
)

Bvh = str | bytes | os.PathLike[str]


def models() -> Steps[list[ModelInfo]]:
    reply: HttpReply = yield Request("GET", "/v1/models")
    return [from_json(ModelInfo, m) for m in reply.body]


def styles(model: str | None) -> Steps[list[StyleInfo]]:
    reply: HttpReply = yield Request("GET", "/v1/styles", params={"model": model} if model else None)
    return [from_json(StyleInfo, s) for s in reply.body]


def style(style_id: str) -> Steps[StyleInfo]:
    reply: HttpReply = yield Request("GET", f"/v1/styles/{style_id}")
    return from_json(StyleInfo, reply.body)


def delete_style(style_id: str) -> Steps[None]:
    yield Request("DELETE", f"/v1/styles/{style_id}")


def upload_style(
    name: str, model: str, bvh: Bvh | None, frames: tuple[np.ndarray, np.ndarray] | None, fps: float, fine_tune: bool
) -> Steps[Upload]:
    """A BVH clip (multipart; `bvh` is the text, its bytes, or a path) or frames (JSON: Hips
    translation (F, 3) and local rotations (F, 22, 4) xyzw in the model's joint order)."""
    if (bvh is None) == (frames is None):
        raise ValueError("upload_style needs exactly one of bvh= or frames=")
    if bvh is not None:
        filename, content = _bvh_file(bvh)
        request = Request(
            "POST",
            "/v1/styles",
            data={"name": name, "model": model, "fine_tune": str(fine_tune).lower()},
            files={"file": (filename, content, "application/octet-stream")},
        )
    else:
        assert frames is not None
        root, rotations = frames
        request = Request(
            "POST",
            "/v1/styles",
            json={
                "name": name,
                "model": model,
                "fps": fps,
                "fine_tune": fine_tune,
                "frames": {
                    "root": np.asarray(root, float).tolist(),
                    "rotations": np.asarray(rotations, float).tolist(),
                },
            },
        )
    reply: HttpReply = yield request
    return Upload.from_json(reply.body, reply.status)


def job(job_id: str) -> Steps[JobInfo]:
    reply: HttpReply = yield Request("GET", f"/v1/jobs/{job_id}")
    return from_json(JobInfo, reply.body)


def _job_polite(job_id: str, poll_interval: float) -> Steps[JobInfo]:
    """The job, after waiting out any 429 with the server's `Retry-After`."""
    while True:
        try:
            return (yield from job(job_id))
        except ServerError as err:
            if err.status != 429:
                raise
            yield Sleep(err.retry_after or poll_interval)


def wait_job(
    job_id: str, progress: Callable[[JobInfo], None] | None, timeout: float | None, poll_interval: float
) -> Steps[JobInfo]:
    """Poll a job until it is done (returned) or failed (`JobFailed`); `progress` sees every change
    of status, progress or message. A 429 waits the server's `Retry-After` and polls again."""
    deadline = None if timeout is None else time.monotonic() + timeout
    seen: tuple[str, float, str] | None = None
    while True:
        info = yield from _job_polite(job_id, poll_interval)
        if progress is not None and (info.status, info.progress, info.message) != seen:
            seen = (info.status, info.progress, info.message)
            progress(info)
        if info.status == "done":
            return info
        if info.status == "failed":
            raise JobFailed(info)
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            raise JobTimeout(f"job {job_id} still {info.status} ({info.progress:.0%}) after {timeout:g} s")
        yield Sleep(poll_interval if left is None else min(poll_interval, left))


def add_style(
    name: str,
    model_names: list[str] | None,
    bvh: Bvh | None,
    frames: tuple[np.ndarray, np.ndarray] | None,
    fps: float,
    fine_tune: bool,
    progress: Callable[[str, JobInfo], None] | None,
    timeout: float | None,
    poll_interval: float,
) -> Steps[dict[str, AddedStyle]]:
    """Upload one clip as style `name` to each of `model_names` (None: every model the server has),
    then follow every job at once, so each style's `live_s` is when it could first be streamed.
    A model that refuses the clip (a bad clip, no training data for a job) is an outcome, not a raise."""
    names = model_names if model_names is not None else [m.name for m in (yield from models())]
    t0 = time.monotonic()
    added: dict[str, AddedStyle] = {}
    jobs: dict[str, tuple[str, StyleInfo]] = {}
    for model in names:
        try:
            upload = yield from upload_style(name, model, bvh, frames, fps, fine_tune)
        except ServerError as err:
            added[model] = AddedStyle(model, error=err)
            continue
        live = time.monotonic() - t0 if upload.created else None
        added[model] = AddedStyle(model, upload.style, live_s=live)
        if upload.job is not None:
            jobs[model] = (upload.job.id, upload.style)
    deadline = None if timeout is None else t0 + timeout
    seen: dict[str, tuple[str, float, str]] = {}
    while jobs:
        for model, (job_id, started) in list(jobs.items()):
            info = yield from _job_polite(job_id, poll_interval)
            if progress is not None and seen.get(model) != (info.status, info.progress, info.message):
                seen[model] = (info.status, info.progress, info.message)
                progress(model, info)
            if info.status in ("done", "failed"):
                del jobs[model]
                now = time.monotonic() - t0
                before = added[model]
                if info.status == "failed":
                    added[model] = AddedStyle(model, before.style, JobFailed(info), before.live_s, now)
                else:
                    ready = yield from style(started.id)
                    added[model] = AddedStyle(model, ready, None, before.live_s or now, now)
        if jobs and deadline is not None and time.monotonic() >= deadline:
            for model, (job_id, _) in jobs.items():
                error = JobTimeout(f"job {job_id} still running after {timeout:g} s (it goes on)")
                added[model] = AddedStyle(model, added[model].style, error, added[model].live_s)
            break
        if jobs:
            yield Sleep(poll_interval)
    return added


def _bvh_file(bvh: Bvh) -> tuple[str, bytes]:
    if isinstance(bvh, bytes):
        return "clip.bvh", bvh
    if isinstance(bvh, str):
        if "HIERARCHY" not in bvh:
            raise ValueError("bvh= as str is the BVH text; pass a pathlib.Path to upload a file")
        return "clip.bvh", bvh.encode()
    path = Path(bvh)
    return path.name, path.read_bytes()
