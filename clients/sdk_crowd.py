"""A crowd on one connection (protocol v1.1, docs/protocol.md#crowds): many characters, one binary
message per tick each way.

`CrowdCore` is the protocol, written once as generators of I/O operations (`sdk_io`); `Crowd` and
`AsyncCrowd` drive it with the sync and asyncio clients. A tick's frames go in as arrays (ids,
roots (n, 3), rotations (n, J, 4) or one (J, 4) array per character where rigs differ) and come
back as one `CrowdFrames`, which slices a character's frame out of the reply without copying.
A refused character (bad rig, unknown style) or frame (NaN) is reported in `errors` with its
character id, and the others go on.
"""

from __future__ import annotations

import json
import logging
import random
import struct
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .sdk_io import (
    AsyncIO,
    Close,
    Connect,
    Disconnected,
    Recv,
    RecvTimeout,
    Send,
    Sleep,
    Steps,
    SyncIO,
    run_async,
    run_sync,
)
from .sdk_session import BACKOFF_FIRST_S, BACKOFF_MAX_S, RETRY_CODES
from .sdk_types import ConnectFailed, ConnectionLost, CrowdReconnect, ResumeError, ServerError

log = logging.getLogger(__name__)

TICK_HEADER = struct.Struct("<IHHI")  # seq, kind (2 = tick), characters, dropped
KIND_TICK = 2
KIND_CONTROL_TICK, CONTROL_FLOATS = 3, 4  # a controller tick: forward, side (m/s), facing (rad), gait (0/1)
REPLAY_MESSAGES = 128  # ticks and controls held to send again after a resume (the server stores every 30 ticks)


@dataclass(frozen=True)
class Character:
    """One member of a crowd: its id (the client's name for it in ticks), model, style and rig."""

    id: int
    model: str
    style: str | None = None
    mix: dict[str, float] | None = None
    intensity: float = 1.0
    skeleton: str | None = "bandai-namco"
    bvh_header: str | None = None
    joints: list[str] | None = None
    resume_token: str | None = None  # continue this character where it left off (`Crowd.resume_tokens`)
    pipeline: str = "full"  # "core": the method's published core alone (docs/protocol.md)

    @classmethod
    def resuming(cls, id: int, model: str, resume_token: str) -> Character:
        """The character `resume_token` was given for, under (new) `id`: its model, style and rig
        are the server's stored ones."""
        return cls(id, model, resume_token=resume_token)

    def message(self) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id, "model": self.model, "intensity": self.intensity}
        if self.pipeline != "full":
            out["pipeline"] = self.pipeline
        if self.resume_token is not None:
            out["resume_token"] = self.resume_token
        out.update({"mix": self.mix} if self.mix is not None else {"style": self.style})
        if self.bvh_header is not None:
            out["bvh_header"] = self.bvh_header
        elif self.skeleton is not None:
            out["skeleton"] = self.skeleton
        if self.joints is not None:
            out["joints"] = self.joints
        return out


@dataclass(frozen=True)
class Sent:
    """A message kept for replay: a tick (`seq`), or a control message and the reply it awaits."""

    data: bytes | str
    seq: int | None = None
    reply: str = ""


@dataclass
class CrowdFrames:
    """One tick's reply: every character's stylised frame, in the tick's order (a character whose
    frame was refused is left out; its error is in the crowd's `errors`)."""

    seq: int
    ids: np.ndarray  # (n,) character ids
    dropped: int  # ticks the server dropped (queue full) since its previous reply
    payload: np.ndarray  # float32: each character's root (3) then rotations (J x 4), end to end
    starts: np.ndarray  # (n,) where each character's frame begins in `payload`
    sizes: np.ndarray  # (n,) floats in each character's frame
    faded: np.ndarray  # (n,) how far each frame faded toward its input (unseen content); 0 for a core pipeline

    def __len__(self) -> int:
        return len(self.ids)

    def frame(self, character: int) -> tuple[np.ndarray, np.ndarray]:
        """(root (3,), rotations (J, 4)) of one character."""
        k = int(np.flatnonzero(self.ids == character)[0])
        chunk = self.payload[self.starts[k] : self.starts[k] + self.sizes[k]]
        return chunk[:3], chunk[3:].reshape(-1, 4)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(roots (n, 3), rotations (n, J, 4)) when every character has the same rig size."""
        if len(self.sizes) and (self.sizes != self.sizes[0]).any():
            raise ValueError("the characters' rigs differ in size: use frame(id)")
        rows = self.payload.reshape(len(self.ids), -1)
        return rows[:, :3], rows[:, 3:].reshape(len(self.ids), -1, 4)


class CrowdCore:
    """What to send and what the replies mean; no I/O of its own (`sdk_io`)."""

    def __init__(
        self,
        url: str,
        headers: dict[str, str],
        characters: Sequence[Character],
        fps: float,
        timeout: float | None,
        reconnect_timeout: float | None = None,
    ) -> None:
        self.url, self.headers, self.fps, self.timeout = url, headers, fps, timeout
        self.reconnect_timeout = reconnect_timeout
        self.opening = list(characters)
        self.members: dict[int, Character] = {}  # as they joined: how to open one again if its token is gone
        self.sent: deque[Sent] = deque(maxlen=REPLAY_MESSAGES)  # recent ticks and controls, to replay after a resume
        self.reconnects = 0
        self.last_reconnect: CrowdReconnect | None = None
        self.frame_floats: dict[int, int] = {}  # per character in the crowd
        self.resume_tokens: dict[int, str] = {}  # per character: where a new crowd can pick it up
        self.resumed: dict[int, int | None] = {}  # characters that resumed: the last tick their snapshot had
        self.errors: list[ServerError] = []  # per-character refusals, in arrival order
        self.crowd_id: str | None = None
        self.seq = 0
        self._arrived: deque[bytes] = deque()  # tick replies that came while waiting for a text reply
        self._layout: tuple[bytes, np.ndarray, np.ndarray] | None = None  # ids bytes -> starts, sizes

    # ---- membership ---------------------------------------------------------------------
    def open(self) -> Steps[dict[str, Any]]:
        yield Connect(self.url, self.timeout, self.headers)
        message = {"type": "crowd", "fps": self.fps, "faded": True, "characters": [c.message() for c in self.opening]}
        yield Send(json.dumps(message))
        reply = yield from self._text_reply("crowd_started")
        self.crowd_id = reply["crowd_id"]
        return self._joined(reply, self.opening)

    def join(self, characters: Sequence[Character]) -> Steps[dict[str, Any]]:
        yield Send(
            self._record("joined", json.dumps({"type": "join", "characters": [c.message() for c in characters]}))
        )
        return self._joined((yield from self._text_reply("joined")), characters)

    def leave(self, ids: Sequence[int]) -> Steps[list[int]]:
        yield Send(self._record("left", json.dumps({"type": "leave", "characters": [int(i) for i in ids]})))
        left = (yield from self._text_reply("left"))["characters"]
        for i in left:
            self.frame_floats.pop(i, None)
            self.resume_tokens.pop(i, None)
            self.members.pop(i, None)
        return left

    def set_style(
        self,
        style: str | None = None,
        characters: Sequence[int] | None = None,
        mix: dict[str, float] | None = None,
        intensity: float = 1.0,
        transition_frames: int = 0,
    ) -> Steps[dict[str, Any]]:
        message: dict[str, Any] = {"type": "style", "intensity": intensity, "transition_frames": transition_frames}
        message.update({"mix": mix} if mix is not None else {"style": style})
        if characters is not None:
            message["characters"] = [int(i) for i in characters]
        yield Send(self._record("style_set", json.dumps(message)))
        return (yield from self._text_reply("style_set"))

    def reset(self, characters: Sequence[int] | None = None) -> Steps[dict[str, Any]]:
        message: dict[str, Any] = {"type": "reset"}
        if characters is not None:
            message["characters"] = [int(i) for i in characters]
        yield Send(self._record("reset_done", json.dumps(message)))
        return (yield from self._text_reply("reset_done"))

    def close(self) -> Steps[None]:
        """End the crowd (`end`, then the server's `ended`, briefly) and close the socket: its
        characters are done and cannot be resumed. A connection that is lost instead leaves
        each character resumable by its token (`resume_tokens`)."""
        try:
            yield Send(json.dumps({"type": "end"}))
            deadline = time.monotonic() + min(self.timeout or 5.0, 5.0)
            while True:
                data = yield Recv(max(0.0, deadline - time.monotonic()))
                if isinstance(data, str) and json.loads(data).get("type") == "ended":
                    break
        except (Disconnected, RecvTimeout):
            pass
        yield Close()

    def _joined(self, reply: dict[str, Any], asked: Sequence[Character]) -> dict[str, Any]:
        by_id = {c.id: c for c in asked}
        for c in reply["characters"]:
            self.members[c["id"]] = by_id[c["id"]]
            self.frame_floats[c["id"]] = reply["rigs"][c["rig"]]["frame_floats"]
            self.resume_tokens[c["id"]] = c["resume_token"]
            if c.get("resumed"):
                self.resumed[c["id"]] = c["last_seq"]
        for e in reply["errors"]:
            self.errors.append(ServerError(e["code"], e["message"], character=e["id"]))
        return reply

    # ---- ticks --------------------------------------------------------------------------
    def encode_tick(self, ids: Sequence[int] | np.ndarray, roots: np.ndarray, rotations: Any) -> bytes:
        """One tick: `rotations` (n, J, 4), or a list of (J_i, 4) arrays where rigs differ."""
        ids = np.asarray(ids, "<u4")
        roots = np.asarray(roots, np.float64).reshape(len(ids), 3)
        if isinstance(rotations, np.ndarray):
            payload = np.concatenate([roots, rotations.reshape(len(ids), -1)], 1)
        else:
            payload = np.concatenate([np.concatenate([r, np.ravel(q)]) for r, q in zip(roots, rotations, strict=True)])
        header = TICK_HEADER.pack(self.seq, KIND_TICK, len(ids), 0)
        self.seq = (self.seq + 1) % 2**32
        return header + ids.tobytes() + payload.astype("<f4").tobytes()

    def encode_control(
        self, ids: Sequence[int] | np.ndarray, velocity: np.ndarray, facing: np.ndarray, gait: Any = "walk"
    ) -> bytes:
        """One controller tick: per character its desired `velocity` (n, 2) [forward, side] m/s,
        `facing` (n,) yaw in radians and `gait` ("walk"/"run", one for all or one each)."""
        ids = np.asarray(ids, "<u4")
        n = len(ids)
        gaits = np.broadcast_to(np.asarray(gait), (n,))
        values = np.empty((n, CONTROL_FLOATS))
        values[:, :2] = np.asarray(velocity, np.float64).reshape(n, 2)
        values[:, 2] = np.broadcast_to(np.asarray(facing, np.float64), (n,))
        values[:, 3] = [1.0 if g in ("run", 1, 1.0) else 0.0 for g in gaits]
        header = TICK_HEADER.pack(self.seq, KIND_CONTROL_TICK, n, 0)
        self.seq = (self.seq + 1) % 2**32
        return header + ids.tobytes() + values.astype("<f4").tobytes()

    def send_tick(self, ids: Sequence[int] | np.ndarray, roots: np.ndarray, rotations: Any) -> Steps[int]:
        """Send a tick without waiting for its reply (pipelined); returns its sequence number."""
        seq = self.seq
        data = self.encode_tick(ids, roots, rotations)
        self.sent.append(Sent(data, seq))
        yield Send(data)
        return seq

    def tick(self, ids: Sequence[int] | np.ndarray, roots: np.ndarray, rotations: Any) -> Steps[CrowdFrames]:
        """Send a tick and wait for its reply (replies come in order). If the connection goes,
        the crowd comes back by itself (`_recover`) and the tick gets its reply from the resumed
        characters, as if nothing had happened."""
        seq = self.seq
        return (yield from self._round_trip(self.encode_tick(ids, roots, rotations), seq))

    def control(
        self, ids: Sequence[int] | np.ndarray, velocity: np.ndarray, facing: np.ndarray, gait: Any = "walk"
    ) -> Steps[CrowdFrames]:
        """A controller tick (LPN-FiLM characters): each listed character's desired motion in, its
        synthesised frame back, as `tick` (and, like it, through a lost connection)."""
        seq = self.seq
        return (yield from self._round_trip(self.encode_control(ids, velocity, facing, gait), seq))

    def _round_trip(self, data: bytes, seq: int) -> Steps[CrowdFrames]:
        self.sent.append(Sent(data, seq))
        try:
            yield Send(data)
        except Disconnected as gone:
            yield from self._recover(gone, seq)
        while True:
            try:
                return (yield from self.receive())
            except Disconnected as gone:
                yield from self._recover(gone, seq)

    # ---- reconnecting ---------------------------------------------------------------------
    def _record(self, reply: str, message: str) -> str:
        self.sent.append(Sent(message, None, reply))
        return message

    def _recover(self, gone: Disconnected, pending: int) -> Steps[None]:
        """Open the crowd again, every character by its resume token (a character whose token the
        server no longer knows joins afresh from its first settings), then send again what the
        stored state lacks: the ticks and style/reset messages after its last answered tick, up to
        and including tick `pending`, whose reply `tick` then reads (the others' are dropped)."""
        if self.reconnect_timeout == 0:
            raise ConnectionLost(f"lost the crowd's connection to {self.url}: {gone}")
        began = time.monotonic()
        yield Close()
        self._arrived.clear()
        reply, attempts = yield from self._reopen(gone)
        answered = [c["last_seq"] for c in reply["characters"] if c.get("resumed")]
        last = min(answered) if answered else None  # a crowd's characters are stored together
        window = self._after(last, pending)
        for entry in window:
            yield Send(entry.data)
            if entry.seq == pending:
                break
            if entry.seq is not None:
                yield from self.receive()  # answered before, lost with the connection: stepped again
            else:
                yield from self._text_reply(entry.reply)
        fresh = [c["id"] for c in reply["characters"] if not c.get("resumed")]
        self.reconnects += 1
        self.last_reconnect = CrowdReconnect(attempts, time.monotonic() - began, last, len(window), fresh, str(gone))
        log.info(
            "crowd back after %d attempt(s): %d message(s) sent again, %d character(s) afresh",
            attempts,
            len(window),
            len(fresh),
        )

    def _after(self, last: int | None, pending: int) -> list[Sent]:
        """What was sent after tick `last` (None: only tick `pending`), or `ResumeError` where that
        cannot be replayed exactly."""
        entries = list(self.sent)
        if last is not None and last >= pending:
            raise ResumeError(f"the reply to tick {pending} went with the connection after the server had stepped it")
        if last is None:
            return [e for e in entries if e.seq == pending]
        at = next((k for k, e in enumerate(entries) if e.seq == last), None)
        if at is None:
            raise ResumeError(f"the messages after tick {last} are no longer held here to send again")
        window = entries[at + 1 :]
        if any(e.reply in ("joined", "left") for e in window):
            raise ResumeError(f"characters joined or left after tick {last}, the last the server had stored")
        if not window or window[-1].seq != pending:
            raise ResumeError("ticks sent ahead without waiting (send_tick) are not resumed by tick()")
        return window

    def _reopen(self, gone: Disconnected) -> Steps[tuple[dict[str, Any], int]]:
        deadline = None if self.reconnect_timeout is None else time.monotonic() + self.reconnect_timeout
        delay, attempts, last_error = BACKOFF_FIRST_S, 0, str(gone)
        while True:
            attempts += 1
            try:
                yield Connect(self.url, self.timeout, self.headers)
                chars = [
                    Character.resuming(i, c.model, self.resume_tokens[i]) if i in self.resume_tokens else c
                    for i, c in self.members.items()
                ]
                yield Send(
                    json.dumps(
                        {"type": "crowd", "fps": self.fps, "faded": True, "characters": [c.message() for c in chars]}
                    )
                )
                reply = yield from self._text_reply("crowd_started")
                busy = [e for e in reply["errors"] if e["code"] in RETRY_CODES]
                if busy:  # e.g. the server has not yet noticed the old connection go: try again shortly
                    raise ServerError(busy[0]["code"], busy[0]["message"], character=busy[0]["id"])
                expired = [e["id"] for e in reply["errors"] if e["code"] == "unknown_resume_token"]
                if expired:  # the store forgot them: they start over with their first settings
                    rejoined = yield from self._rejoin(expired)
                    offset = len(reply["rigs"])  # the rejoin's rig indices count in its own reply
                    reply["characters"] += [{**c, "rig": c["rig"] + offset} for c in rejoined["characters"]]
                    reply["rigs"] += rejoined["rigs"]
                    reply["errors"] = [e for e in reply["errors"] if e["id"] not in expired] + rejoined["errors"]
                self.crowd_id = reply["crowd_id"]
                back = {c["id"] for c in reply["characters"]}
                for i in [i for i in self.members if i not in back]:  # refused now (its error is in `errors`)
                    self.members.pop(i)
                    self.frame_floats.pop(i, None)
                    self.resume_tokens.pop(i, None)
                self._joined(reply, list(self.members.values()))
                return reply, attempts
            except ServerError as err:
                if err.code not in RETRY_CODES:
                    raise
                last_error = str(err)
                yield Close()
            except (Disconnected, RecvTimeout, ConnectFailed) as err:
                last_error = str(err)
                yield Close()
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise ConnectionLost(
                    f"lost the crowd's connection to {self.url} ({gone}) and could not get back within "
                    f"{self.reconnect_timeout:g} s ({attempts} attempts): {last_error}"
                )
            pause = delay * random.uniform(0.5, 1.0)
            yield Sleep(pause if left is None else min(pause, left))
            delay = min(delay * 2, BACKOFF_MAX_S)

    def _rejoin(self, ids: list[int]) -> Steps[dict[str, Any]]:
        for i in ids:
            self.resume_tokens.pop(i, None)
        yield Send(json.dumps({"type": "join", "characters": [self.members[i].message() for i in ids]}))
        return (yield from self._text_reply("joined"))

    def receive(self) -> Steps[CrowdFrames]:
        """The next tick reply (text messages met on the way are errors, recorded or raised)."""
        while not self._arrived:
            message = yield Recv(self.timeout)
            if isinstance(message, bytes):
                self._arrived.append(message)
            else:
                self._text(json.loads(message))
        return self.decode_reply(self._arrived.popleft())

    def decode_reply(self, data: bytes) -> CrowdFrames:
        seq, kind, count, dropped = TICK_HEADER.unpack_from(data)
        if kind != KIND_TICK:
            raise ServerError("bad_reply", f"expected a tick reply (kind {KIND_TICK}), got kind {kind}")
        ids_raw = data[TICK_HEADER.size : TICK_HEADER.size + 4 * count]
        ids = np.frombuffer(ids_raw, "<u4")
        if self._layout is None or self._layout[0] != ids_raw:  # worked out once per list of characters
            sizes = np.array([self.frame_floats[int(i)] for i in ids], np.int64)
            self._layout = (bytes(ids_raw), np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64), sizes)
        _, starts, sizes = self._layout
        floats = np.frombuffer(data, "<f4", offset=TICK_HEADER.size + 4 * count)
        end = int(sizes.sum())  # the frames, then (a crowd opened with `faded`) one float per character
        faded = floats[end : end + count] if len(floats) > end else np.zeros(count, np.float32)
        return CrowdFrames(seq, ids, dropped, floats[:end], starts, sizes, faded)

    # ---- text replies -------------------------------------------------------------------
    def _text_reply(self, kind: str) -> Steps[dict[str, Any]]:
        while True:
            message = yield Recv(self.timeout)
            if isinstance(message, bytes):
                self._arrived.append(message)
                continue
            reply = json.loads(message)
            if reply.get("type") == kind:
                return reply
            self._text(reply)

    def _text(self, reply: dict[str, Any]) -> None:
        if reply.get("type") != "error":
            return  # a reply no call waits for (e.g. a `left` after a timed-out call)
        error = ServerError(reply["code"], reply["message"], reply.get("seq"), character=reply.get("character"))
        if error.character is None:
            raise error
        self.errors.append(error)


class _CrowdState:
    core: CrowdCore

    @property
    def crowd_id(self) -> str | None:
        return self.core.crowd_id

    @property
    def errors(self) -> list[ServerError]:
        """Per-character refusals so far (join errors, refused frames, deleted styles)."""
        return self.core.errors

    @property
    def characters(self) -> list[int]:
        return list(self.core.frame_floats)

    @property
    def reconnects(self) -> int:
        """Times the crowd came back by itself after its connection went (`tick`)."""
        return self.core.reconnects

    @property
    def last_reconnect(self) -> CrowdReconnect | None:
        return self.core.last_reconnect

    @property
    def resume_tokens(self) -> dict[int, str]:
        """Each character's resume token: after a lost connection or a server restart (1012), a
        new crowd continues them exactly with `Character.resuming(id, model, token)`."""
        return dict(self.core.resume_tokens)

    @property
    def resumed(self) -> dict[int, int | None]:
        """Characters this crowd resumed, with the last tick their stored state had answered."""
        return dict(self.core.resumed)


class Crowd(_CrowdState):
    """A crowd with the sync client: `tick` sends one tick and returns its reply."""

    def __init__(self, core: CrowdCore) -> None:
        self.core, self.io = core, SyncIO()
        run_sync(core.open(), self.io)

    def tick(self, ids: Sequence[int] | np.ndarray, roots: np.ndarray, rotations: Any) -> CrowdFrames:
        return run_sync(self.core.tick(ids, roots, rotations), self.io)

    def send_tick(self, ids: Sequence[int] | np.ndarray, roots: np.ndarray, rotations: Any) -> int:
        return run_sync(self.core.send_tick(ids, roots, rotations), self.io)

    def control(self, ids: Sequence[int] | np.ndarray, velocity: Any, facing: Any, gait: Any = "walk") -> CrowdFrames:
        return run_sync(self.core.control(ids, velocity, facing, gait), self.io)

    def receive(self) -> CrowdFrames:
        return run_sync(self.core.receive(), self.io)

    def join(self, characters: Sequence[Character]) -> dict[str, Any]:
        return run_sync(self.core.join(characters), self.io)

    def leave(self, ids: Sequence[int]) -> list[int]:
        return run_sync(self.core.leave(ids), self.io)

    def set_style(self, style: str | None = None, characters: Sequence[int] | None = None, **options: Any) -> dict:
        return run_sync(self.core.set_style(style, characters, **options), self.io)

    def reset(self, characters: Sequence[int] | None = None) -> dict[str, Any]:
        return run_sync(self.core.reset(characters), self.io)

    def close(self) -> None:
        run_sync(self.core.close(), self.io)

    def __enter__(self) -> Crowd:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncCrowd(_CrowdState):
    """A crowd with the asyncio client (`await AsyncClient.crowd(...)` or `async with`)."""

    def __init__(self, core: CrowdCore) -> None:
        self.core, self.io = core, AsyncIO()

    async def open(self) -> AsyncCrowd:
        await run_async(self.core.open(), self.io)
        return self

    async def tick(self, ids: Sequence[int] | np.ndarray, roots: np.ndarray, rotations: Any) -> CrowdFrames:
        return await run_async(self.core.tick(ids, roots, rotations), self.io)

    async def send_tick(self, ids: Sequence[int] | np.ndarray, roots: np.ndarray, rotations: Any) -> int:
        return await run_async(self.core.send_tick(ids, roots, rotations), self.io)

    async def control(
        self, ids: Sequence[int] | np.ndarray, velocity: Any, facing: Any, gait: Any = "walk"
    ) -> CrowdFrames:
        return await run_async(self.core.control(ids, velocity, facing, gait), self.io)

    async def receive(self) -> CrowdFrames:
        return await run_async(self.core.receive(), self.io)

    async def join(self, characters: Sequence[Character]) -> dict[str, Any]:
        return await run_async(self.core.join(characters), self.io)

    async def leave(self, ids: Sequence[int]) -> list[int]:
        return await run_async(self.core.leave(ids), self.io)

    async def set_style(
        self, style: str | None = None, characters: Sequence[int] | None = None, **options: Any
    ) -> dict:
        return await run_async(self.core.set_style(style, characters, **options), self.io)

    async def reset(self, characters: Sequence[int] | None = None) -> dict[str, Any]:
        return await run_async(self.core.reset(characters), self.io)

    async def close(self) -> None:
        await run_async(self.core.close(), self.io)

    async def __aenter__(self) -> AsyncCrowd:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
