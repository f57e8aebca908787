"""Decoding an uploaded style clip away from the event loop, within a time and memory budget.

A clip is parsed (BVH text or JSON frames), retargeted and resampled to the model rate before it
can become a style. That is CPU work proportional to what the client *declares* (a BVH `Frame
Time: 10` resampled to 30 fps is 300x its rows; a JSON `fps: 0.0001` asks for millions of
frames), so it is refused early and run late:

- `check_rate` refuses a frame rate outside [upload_min_fps, upload_max_fps] and a clip whose
  length *at 30 fps* falls outside the frame limits, from the declared count and rate, before
  anything is resampled (typed 422, never an allocation);
- `ClipDecoder` runs the decoding in child processes forked from a preloaded server
  (multiprocessing's forkserver, so the server's threads are never forked), at the background's
  CPU priority and on its CPUs, capped in address space and in CPU time: the event loop only
  waits on a pipe, no upload can stall the streams, and a clip that still exhausts its budget
  costs its own child (413 / 422), never the server. A child that answered takes the next clip:
  starting processes was itself what the streams felt.

The time budget is CPU time, counted by the child itself, because what a clip costs is the
clip's doing and how long it waits for a core is not: at a low priority beside busy processes a
child gets a sliver of a core, and a wall-clock deadline refused valid clips as "too slow" on a
loaded machine. A wall-clock limit remains, far longer, for a server too busy to decode at all
(503).
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import multiprocessing.forkserver
import os
import pickle
import resource
import signal
import threading
from collections.abc import AsyncGenerator, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, Literal

import numpy as np
from starlette.datastructures import Headers
from starlette.formparsers import MultiPartParser

from models.motion import bvh as bvhio
from models.motion.resample import resampled_length
from models.motion.skeleton import Motion, Skeleton

from .api import ApiError, StyleUpload
from .background import Placement, background_placement, enter_background, in_background, pieces
from .clips import MODEL_FPS, motion_from_bvh, motion_from_json
from .memory import release_freed_memory

Kind = Literal["bvh", "json"]  # what a style was made from (`StyleInfo.source`)
Upload = Literal["multipart", "json"]  # how its clip came: a form with a BVH file part, or JSON frames
Body = list[bytes]  # a request body as the non-empty chunks it was read in (joined in the child)


@dataclass(frozen=True)
class ClipBudget:
    """What one upload may cost: frame limits at 30 fps, the accepted rates, CPU time and memory,
    and how long the server waits for its answer however busy the machine."""

    min_frames: int
    max_frames: int
    min_fps: float
    max_fps: float
    cpu_s: float
    memory_mb: int
    wall_s: float


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


class _PartsInMemory(MultiPartParser):
    """Starlette's multipart parser, keeping file parts in memory: the whole body is in memory
    already, and spilling a 15 MB part to a temporary file (Starlette's default above 1 MB) put
    disk writes behind every large upload, which the streams felt (issue #16)."""

    spool_max_size = 1 << 62


def read_multipart(body: bytes, content_type: str) -> tuple[bytes, dict[str, Any]]:
    """A multipart upload's BVH `file` part and its text fields (`fine_tune` as a bool), parsed
    as the route would parse a form (Starlette's parser), but here in the child: a 15 MB form
    costs the event loop nothing but reading its bytes."""

    async def chunks() -> AsyncGenerator[bytes, None]:
        yield body

    async def parse() -> tuple[bytes, dict[str, Any]]:
        try:
            form = await _PartsInMemory(Headers({"content-type": content_type}), chunks()).parse()
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


class _OverBudget(BaseException):
    """Raised in the child by its CPU timer. A BaseException, so that no `except Exception` on
    the decoding path (the multipart parser's, the catch-all below) takes it for the clip's own
    error."""


@contextlib.contextmanager
def cpu_budget(seconds: float) -> Iterator[None]:
    """Raise `_OverBudget` once this process has used `seconds` of CPU inside the block (a
    profiling timer: it counts CPU time, not the time spent waiting for a core). Main thread
    only, as every Python signal handler."""

    def expire(signum: int, frame: object) -> None:
        raise _OverBudget

    previous = signal.signal(signal.SIGPROF, expire)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, previous)  # a timer that fired but was not yet handled is dropped


MAX_CLIPS_PER_CHILD = 200  # then a fresh child: what a long run of clips left in its heap goes back


def _decode_one(
    conn: Connection,
    kind: Upload | Kind,
    fields: dict[str, Any],
    skeletons: dict[str, Skeleton],
    content_type: str,
    budget: ClipBudget,
    last: bool,
) -> bool:
    """Receive one clip's body (its chunks, then an empty message), decode it and answer
    (status, payload, retiring); True, and said in the answer, when this child takes no other
    clip: its `last`, or one that ran out of its memory or CPU budget (what that left, perhaps
    half-built, is not kept)."""
    retire = last
    try:
        body = b"".join(iter(conn.recv_bytes, b""))
        with cpu_budget(budget.cpu_s):
            clip = decode_clip(kind, body, fields, skeletons, budget, content_type)
        answer: tuple = ("ok", clip)
    except ApiError as err:
        answer = ("error", (err.status, err.code, err.message))
    except _OverBudget:
        message = f"decoding the clip took more than {budget.cpu_s:g} s of CPU; send a shorter one"
        answer = ("error", (422, "clip_too_slow", message))
        retire = True
    except MemoryError:
        answer = ("error", (413, "clip_too_large", f"decoding the clip needs more than {budget.memory_mb} MB"))
        retire = True
    except Exception as exc:  # noqa: BLE001  (whatever else a hostile file provokes is still the file's fault)
        answer = ("error", (422, "bad_clip", f"the clip could not be decoded: {type(exc).__name__}: {exc}"[:500]))
    send_answer(conn, (*answer, retire))
    return retire


def send_answer(conn: Connection, answer: tuple) -> None:
    """Pickle `answer` with its arrays out of band (protocol 5) and send the arrays' bytes in
    pieces, so the reader never holds the GIL for long (`receive_answer`)."""
    buffers: list[pickle.PickleBuffer] = []
    conn.send_bytes(pickle.dumps(answer, protocol=5, buffer_callback=buffers.append))
    conn.send([len(b.raw()) for b in buffers])
    for buffer in buffers:
        for piece in pieces(buffer.raw()):
            conn.send_bytes(piece)


def receive_answer(conn: Connection) -> tuple:
    """What `send_answer` sent. Unpickling a decoded clip in one go (~6 MB of arrays for the
    longest) is one C call that holds the GIL, and with it the event loop, for its whole copy,
    whatever the switch interval; read piece by piece, no hold is longer than one piece's copy,
    and the arrays are made over the buffers they were read into, without another copy."""
    head = conn.recv_bytes()
    buffers = [np.empty(size, np.uint8) for size in conn.recv()]  # not zeroed first: the reads fill them
    for buffer in buffers:
        for piece in pieces(buffer.data):  # the very pieces `send_answer` sent
            conn.recv_bytes_into(piece)
    return pickle.loads(head, buffers=buffers)


def _child(conn: Connection, memory_mb: int, where: Placement) -> None:
    """A decoding child: clips one after another until the server closes the pipe, it has done
    `MAX_CLIPS_PER_CHILD` or one exhausted its memory or CPU budget. It lives on between uploads
    because starting a process is what cost the streams: 7-10 forks a second, even of an empty
    child from another process, tripled a healthy session's round-trip p99 on the 2-core test
    machine (`clients.hostile_bench`, docs/deploy.md). Each clip comes with its budget; the
    address-space cap (`memory_mb`) is set once, at start."""
    enter_background(where)  # the streams' cores are theirs first (`background`)
    _cap_memory(memory_mb)
    try:
        for done in range(MAX_CLIPS_PER_CHILD):
            try:
                kind, fields, skeletons, content_type, budget = conn.recv()
            except EOFError:  # the server is done with this child
                return
            if _decode_one(conn, kind, fields, skeletons, content_type, budget, done == MAX_CLIPS_PER_CHILD - 1):
                return
            release_freed_memory()
    finally:
        conn.close()


@dataclass
class _Child:
    process: BaseProcess
    conn: Connection


class ClipDecoder:
    """Runs `decode_clip` in child processes, at most `concurrency` at a time (others wait). A
    child that answered is kept for the next clip; one that has not answered by the wall-clock
    limit is killed."""

    def __init__(self, budget: ClipBudget, concurrency: int = 2) -> None:
        self.budget = budget
        self._slots = asyncio.Semaphore(concurrency)
        self._context = multiprocessing.get_context("forkserver")
        self._context.set_forkserver_preload([__name__])  # children start with numpy, scipy and the parsers loaded
        # The fork server starts now, from the thread building the app: started by the first
        # upload's waiting thread it inherited that thread's niceness (19 then), and its
        # imports (~1.4 s of CPU) waited behind every busy process on the machine: beside four
        # spinning processes the first upload was still unanswered after 30 s.
        multiprocessing.forkserver.ensure_running()
        self._idle: list[_Child] = []
        self._lock = threading.Lock()
        self.started = 0  # children started so far

    async def decode(
        self,
        kind: Upload | Kind,
        body: Body,
        fields: dict[str, Any],
        skeletons: dict[str, Skeleton],
        content_type: str = "",
    ) -> DecodedClip:
        async with self._slots:
            return await in_background(self._run, kind, body, fields, skeletons, content_type)

    def close(self) -> None:
        """Let the idle children go (they exit when their pipe closes)."""
        with self._lock:
            idle, self._idle = self._idle, []
        for child in idle:
            self._reap(child, timeout=5.0)

    def _take(self) -> _Child:
        with self._lock:
            while self._idle:
                child = self._idle.pop()
                if child.process.is_alive():
                    return child
                self._reap(child)
        receiver, sender = self._context.Pipe(duplex=True)
        process = self._context.Process(
            target=_child, args=(sender, self.budget.memory_mb, background_placement()), daemon=True
        )
        process.start()
        sender.close()
        with self._lock:
            self.started += 1
        return _Child(process, receiver)

    @staticmethod
    def _reap(child: _Child, timeout: float = 0.0) -> None:
        child.conn.close()
        child.process.join(timeout)
        if child.process.is_alive():
            child.process.kill()
            child.process.join()

    def _run(
        self,
        kind: Upload | Kind,
        body: Body,
        fields: dict[str, Any],
        skeletons: dict[str, Skeleton],
        content_type: str,
    ) -> DecodedClip:
        """A background thread: hand a child the clip, wait for its answer or the deadline. The
        body goes through the pipe chunk by chunk, not pickled with the job: pipe writes let go
        of the GIL, pickling 15 MB would hold the event loop."""
        child, keep, answered = self._take(), False, False
        try:
            try:
                child.conn.send((kind, fields, skeletons, content_type, self.budget))
                for chunk in (*body, b""):  # non-empty chunks, then the end
                    child.conn.send_bytes(chunk)
            except OSError:  # the child is gone (over its memory budget at start)
                pass
            if not child.conn.poll(self.budget.wall_s):  # within its CPU budget, but given no core to use it
                raise ApiError(
                    503,
                    "server_busy",
                    f"the server is too busy to decode the clip (not done after {self.budget.wall_s:g} s); "
                    "try again later",
                    {"Retry-After": "30"},
                )
            try:
                status, payload, retiring = receive_answer(child.conn)
            except EOFError:  # the child died without answering (killed for memory)
                raise ApiError(413, "clip_too_large", "decoding the clip ran out of its memory budget") from None
            answered, keep = True, not retiring
        finally:
            if keep:
                with self._lock:
                    self._idle.append(child)
            else:  # past its deadline (killed), or retiring (it exits by itself)
                self._reap(child, timeout=1.0 if answered else 0.0)
        if status == "error":
            raise ApiError(*payload)
        return payload
