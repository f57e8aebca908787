"""Decoding an uploaded style clip away from the event loop, within a time and memory budget.

A clip is parsed (BVH text or JSON frames), retargeted and resampled to the model rate before it
can become a style. That is CPU work proportional to what the client *declares* (a BVH `Frame
Time: 10` resampled to 30 fps is 300x its rows; a JSON `fps: 0.0001` asks for millions of
frames), so it is refused early and run late:

- `check_rate` refuses a frame rate outside [upload_min_fps, upload_max_fps] and a clip whose
  length *at 30 fps* falls outside the frame limits, from the declared count and rate, before
  anything is resampled (typed 422, never an allocation);
- `ClipDecoder` runs the decoding in a child process forked from a preloaded server
  (multiprocessing's forkserver, so the server's threads are never forked), capped in address
  space and killed after `upload_decode_timeout_s`: the event loop only waits on a pipe, no
  upload can stall the streams, and a clip that still exhausts its budget costs its own child
  (413 / 422), never the server.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import resource
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Literal

from starlette.requests import Request

from models.motion import bvh as bvhio
from models.motion.resample import resampled_length
from models.motion.skeleton import Motion, Skeleton

from .api import ApiError, StyleUpload
from .clips import MODEL_FPS, motion_from_bvh, motion_from_json

DECODE_NICENESS = 10  # the decoding child's CPU priority below the server's (Linux nice)
Kind = Literal["bvh", "json"]  # what a style was made from (`StyleInfo.source`)
Upload = Literal["multipart", "json"]  # how its clip came: a form with a BVH file part, or JSON frames


@dataclass(frozen=True)
class ClipBudget:
    """What one upload may cost: frame limits at 30 fps, the accepted rates, time and memory."""

    min_frames: int
    max_frames: int
    min_fps: float
    max_fps: float
    timeout_s: float
    memory_mb: int


@dataclass
class DecodedClip:
    """An upload's fields (name, model, fine_tune as sent) and, once its model is known to take
    uploads, its clip on that model's skeleton at 30 fps and the rig it came from."""

    fields: dict[str, Any] = field(default_factory=dict)
    motion: Motion | None = None
    rig: str = ""
    source: Kind = "bvh"


def check_rate(num_frames: int, fps: float, budget: ClipBudget) -> None:
    """Refuse (typed 422) a rate outside the accepted range or a clip whose length at 30 fps is
    outside the frame limits, before any of it is resampled."""
    if not budget.min_fps <= fps <= budget.max_fps:
        raise ApiError(
            422,
            "bad_frame_rate",
            f"the clip's frame rate {fps:.6g} fps is outside {budget.min_fps:g}-{budget.max_fps:g} fps "
            f"(BVH 'Frame Time' {1 / budget.max_fps:.6g}-{1 / budget.min_fps:.6g} s)",
        )
    n, lo, hi = resampled_length(num_frames, fps, MODEL_FPS), budget.min_frames, budget.max_frames
    if not lo <= n <= hi:
        raise ApiError(
            422,
            "bad_length",
            f"the clip has {n} frames at 30 fps ({num_frames} at {fps:.6g} fps); {lo}-{hi} are needed",
        )


def read_multipart(body: bytes, content_type: str) -> tuple[bytes, dict[str, Any]]:
    """A multipart upload's BVH `file` part and its text fields (`fine_tune` as a bool), parsed
    as the route would parse a form (Starlette's parser), but here in the child: a 15 MB form
    costs the event loop nothing but reading its bytes."""

    async def receive() -> dict:
        return {"type": "http.request", "body": body, "more_body": False}

    async def parse() -> tuple[bytes, dict[str, Any]]:
        scope = {"type": "http", "method": "POST", "headers": [(b"content-type", content_type.encode("latin-1"))]}
        try:
            form = await Request(scope, receive).form()
        except MemoryError:
            raise  # over the child's budget: 413, as for the clip itself
        except Exception as exc:  # noqa: BLE001
            raise ApiError(422, "bad_request", f"unreadable multipart body: {exc}") from None
        file = form.get("file")
        if file is None or isinstance(file, str):
            raise ApiError(422, "bad_request", "multipart upload needs a 'file' part with the BVH clip")
        fields: dict[str, Any] = {k: v for k, v in form.items() if isinstance(v, str)}
        fields["name"] = fields.get("name", "")
        fields["fine_tune"] = fields.get("fine_tune", "false").lower() in ("1", "true", "yes", "on")
        return await file.read(), fields

    return asyncio.run(parse())


def decode_clip(
    kind: Upload | Kind,
    body: bytes,
    fields: dict[str, Any],
    skeletons: dict[str, Skeleton],
    budget: ClipBudget,
    content_type: str = "",
) -> DecodedClip:
    """The upload's clip on the skeleton of the model it names (in `skeletons`: the models that
    take uploads); `fields` (the query's name, model, fine_tune) override the upload's own. Runs
    in the child; every refusal is an `ApiError`."""
    if kind == "json":
        try:
            upload = StyleUpload.model_validate_json(body)
        except ValueError as exc:
            raise ApiError(422, "bad_request", f"invalid JSON upload: {str(exc)[:500]}") from None
        fields = {"name": upload.name, "model": upload.model, "fine_tune": upload.fine_tune, **fields}
        skeleton = skeletons.get(fields["model"])
        if skeleton is None:  # the style store says why (unknown model, or one without uploads)
            return DecodedClip(fields, source="json")
        check_rate(len(upload.frames.root), upload.fps, budget)
        motion, rig = motion_from_json(upload, skeleton)
        return DecodedClip(fields, motion, rig, "json")
    if kind == "multipart":
        body, form = read_multipart(body, content_type)
        fields = {**form, **fields}
    skeleton = skeletons.get(fields.get("model") or "lti")
    if skeleton is None:
        return DecodedClip(fields)
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise ApiError(422, "bad_bvh", "the BVH file is not UTF-8 text") from None
    try:
        parsed = bvhio.parse(text, "upload.bvh")
    except bvhio.BvhError as exc:
        raise ApiError(422, "bad_bvh", f"not a readable BVH file: {exc}") from None
    check_rate(parsed.num_frames, 1.0 / parsed.frame_time, budget)
    motion, rig = motion_from_bvh(text, skeleton, parsed)
    return DecodedClip(fields, motion, rig)


# ---- the child process --------------------------------------------------------------------------


def _cap_memory(extra_mb: int) -> None:
    """Cap the child's address space at what it has (inherited from the preloaded server) plus
    `extra_mb`, so a clip that needs more fails with MemoryError in the child alone."""
    with open("/proc/self/statm") as f:
        size = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    limit = size + extra_mb * 1024 * 1024
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def _child(
    conn: Connection,
    kind: Upload | Kind,
    fields: dict[str, Any],
    skeletons: dict[str, Skeleton],
    budget: ClipBudget,
    content_type: str,
) -> None:
    try:
        os.nice(DECODE_NICENESS)  # the streams' event loop gets the core first when both want it
        _cap_memory(budget.memory_mb)
        body = conn.recv_bytes()
        conn.send(("ok", decode_clip(kind, body, fields, skeletons, budget, content_type)))
    except ApiError as err:
        conn.send(("error", (err.status, err.code, err.message)))
    except MemoryError:
        conn.send(("error", (413, "clip_too_large", f"decoding the clip needs more than {budget.memory_mb} MB")))
    except Exception as exc:  # noqa: BLE001  (whatever else a hostile file provokes is still the file's fault)
        conn.send(("error", (422, "bad_clip", f"the clip could not be decoded: {type(exc).__name__}: {exc}"[:500])))
    finally:
        conn.close()


class ClipDecoder:
    """Runs `decode_clip` in child processes, at most `concurrency` at a time (others wait)."""

    def __init__(self, budget: ClipBudget, concurrency: int = 2) -> None:
        self.budget = budget
        self._slots = asyncio.Semaphore(concurrency)
        self._context = multiprocessing.get_context("forkserver")
        self._context.set_forkserver_preload([__name__])  # children start with numpy, scipy and the parsers loaded

    async def decode(
        self,
        kind: Upload | Kind,
        body: bytes | bytearray,
        fields: dict[str, Any],
        skeletons: dict[str, Skeleton],
        content_type: str = "",
    ) -> DecodedClip:
        async with self._slots:
            return await asyncio.to_thread(self._run, kind, body, fields, skeletons, content_type)

    def _run(
        self,
        kind: Upload | Kind,
        body: bytes | bytearray,
        fields: dict[str, Any],
        skeletons: dict[str, Skeleton],
        content_type: str,
    ) -> DecodedClip:
        """A worker thread: start the child, send it the body, wait for its answer or the
        deadline, reap it. The body goes through the pipe, not with the child's arguments: a
        pipe write of 15 MB lets go of the GIL, pickling it would hold the event loop."""
        receiver, sender = self._context.Pipe(duplex=True)
        child = self._context.Process(
            target=_child, args=(sender, kind, fields, skeletons, self.budget, content_type), daemon=True
        )
        child.start()
        sender.close()
        try:
            try:
                receiver.send_bytes(body)
            except OSError:  # the child is already gone (over its memory budget at start)
                pass
            if not receiver.poll(self.budget.timeout_s):
                raise ApiError(
                    422,
                    "clip_too_slow",
                    f"decoding the clip took longer than {self.budget.timeout_s:g} s; send a shorter one",
                )
            try:
                status, payload = receiver.recv()
            except EOFError:  # the child died without answering (killed for memory)
                raise ApiError(413, "clip_too_large", "decoding the clip ran out of its memory budget") from None
        finally:
            receiver.close()
            if child.is_alive():
                child.kill()
            child.join()
        if status == "error":
            raise ApiError(*payload)
        return payload
