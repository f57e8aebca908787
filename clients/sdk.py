"""Python SDK for the stylestream service: REST calls and streaming sessions, sync and async.

    from clients.sdk import Client

    client = Client("http://127.0.0.1:8000")
    print(client.models())
    with client.session(model="lti", style="elderly") as s:
        for root, rotations in frames:               # root (3,), rotations (J, 4) xyzw
            out = s.stylise(root, rotations)          # one frame in, one frame out
        s.set_style("exhausted", transition_frames=30)

    # asyncio
    async with AsyncClient("http://127.0.0.1:8000").session(model="lti", style="elderly") as s:
        out = await s.stylise(root, rotations)

Frames travel as binary (docs/protocol.md). A session that loses its connection (a dropped
network, a replica drained with 1012 or killed) reconnects with its resume token by itself, to
whichever replica the address leads to, and replays what the server's last stored snapshot
lacks: the frames and style changes sent since (kept in a bounded `ReplayBuffer`, trimmed by
the server's snapshot acknowledgements). Replies it already has are discarded, so the outputs
equal an uninterrupted run's.
"""

from __future__ import annotations

import asyncio
import json
import struct
import time
from collections import deque
from contextlib import ExitStack
from dataclasses import dataclass

import httpx
import numpy as np
from pydantic import BaseModel

HEADER = struct.Struct("<IHH")
RESUME_ATTEMPTS = 8  # connection attempts per resume: the server may not have seen the old connection
RESUME_BACKOFF_S = 0.05  # go yet, the load balancer may pick a draining replica, a replica may be restarting
RETRY_CODES = {"session_in_use", "draining", "store_unavailable"}
REPLAY_LIMIT = 1024  # messages kept for replay; a server acknowledges a snapshot every 30 frames by default


class ModelInfo(BaseModel):
    name: str
    styles: list[str]
    joints: list[str]
    controllable: bool = False  # sessions may send `control` ticks (Session.control) instead of frames


class ServerError(RuntimeError):
    """A typed error message from the server."""

    def __init__(self, code: str, message: str, seq: int | None = None) -> None:
        super().__init__(f"{code}: {message}")
        self.code, self.message, self.seq = code, message, seq


class ResumeError(RuntimeError):
    """The session cannot continue exactly: the server's snapshot and the messages this client
    still holds do not meet (the replay buffer overflowed while the server stored no snapshot,
    or a reply was lost after the server had saved its frame)."""


class ReplayBuffer:
    """The messages sent since the last snapshot the server acknowledged, in order, so a resumed
    session can be brought up to date. Frames are binary messages with their sequence number;
    control messages (style, reset) are text. Replaying a control message the snapshot already
    holds is harmless: without a frame in between it sets the same target and ramp again.

    `base` is the sequence number of the frame just before the first entry (None: the session's
    start); a snapshot at `base` or at any buffered frame can be continued."""

    def __init__(self, limit: int = REPLAY_LIMIT) -> None:
        self.entries: deque[tuple[int | None, bytes | str]] = deque()
        self.limit = limit
        self.base: int | None = None

    def add(self, seq: int | None, message: bytes | str) -> None:
        self.entries.append((seq, message))
        if len(self.entries) > self.limit:
            self._drop_through(next(s for s, _ in self.entries if s is not None))

    def acknowledged(self, last_seq: int) -> None:
        """The server stored a snapshot covering frames up to `last_seq`: forget them."""
        if any(s == last_seq for s, _ in self.entries):
            self._drop_through(last_seq)

    def after(self, last_seq: int | None) -> list[tuple[int | None, bytes | str]]:
        """What to send again to a session restored at `last_seq`."""
        if last_seq == self.base:
            return list(self.entries)
        for i, (seq, _) in enumerate(self.entries):
            if seq is not None and seq == last_seq:
                return list(self.entries)[i + 1:]
        raise ResumeError(f"the server resumed at frame {last_seq}, but this client only holds messages after frame "
                          f"{self.base}: more than {self.limit} messages went unacknowledged")

    def _drop_through(self, seq: int) -> None:
        while self.entries:
            s, _ = self.entries.popleft()
            if s == seq:
                self.base = seq
                return


@dataclass
class StyledFrame:
    seq: int
    root: np.ndarray  # (3,)
    rotations: np.ndarray  # (J, 4)
    dropped: int  # frames the server dropped before this one (backpressure)


def _start_message(model: str, style: str | None, mix: dict[str, float] | None, skeleton: str | None,
                   bvh_header: str | None, fps: float, intensity: float, resume_token: str | None) -> str:
    msg = {"type": "start", "model": model, "fps": fps, "encoding": "binary", "intensity": intensity}
    if mix is not None:
        msg["mix"] = mix
    else:
        msg["style"] = style
    if bvh_header is not None:
        msg["bvh_header"] = bvh_header
    elif skeleton is not None:
        msg["skeleton"] = skeleton
    if resume_token:
        msg["resume_token"] = resume_token
    msg["snapshot_acks"] = True  # the replay buffer forgets what a stored snapshot covers
    return json.dumps(msg)


def _style_message(style: str | None, mix: dict[str, float] | None, intensity: float, transition_frames: int) -> str:
    msg = {"type": "style", "intensity": intensity, "transition_frames": transition_frames}
    msg.update({"mix": mix} if mix is not None else {"style": style})
    return json.dumps(msg)


def _control_message(seq: int, velocity: tuple[float, float], facing: float, gait: str) -> str:
    return json.dumps({"type": "control", "seq": seq, "velocity": [float(velocity[0]), float(velocity[1])],
                       "facing": float(facing), "gait": gait})


def _pack(seq: int, root: np.ndarray, rotations: np.ndarray) -> bytes:
    return HEADER.pack(seq & 0xFFFFFFFF, 1, 0) + np.concatenate([np.ravel(root), np.ravel(rotations)]).astype("<f4").tobytes()


def _unpack(data: bytes, joints: int) -> StyledFrame:
    seq, _, dropped = HEADER.unpack_from(data)
    values = np.frombuffer(data, "<f4", offset=HEADER.size).astype(np.float64)
    return StyledFrame(seq, values[:3], values[3:].reshape(joints, 4), dropped)


def _saved_reply(started: dict, seq: int | None) -> StyledFrame | None:
    """The reply to frame `seq` as the server saved it with the snapshot (`started.last_frame`):
    the server had processed the frame when the connection went, but its reply never arrived.
    Rounded to float32 like a binary reply."""
    last = started.get("last_frame")
    if seq is None or last is None or last["seq"] != seq:
        return None
    return StyledFrame(seq, np.asarray(last["root"], np.float32).astype(np.float64),
                       np.asarray(last["rotations"], np.float32).astype(np.float64), 0)


def _raise_if_error(message: dict) -> dict:
    if message.get("type") == "error":
        raise ServerError(message.get("code", "error"), message.get("message", ""), message.get("seq"))
    return message


def _ws_url(base_url: str, token: str | None) -> str:
    url = base_url.rstrip("/").replace("http://", "ws://").replace("https://", "wss://") + "/v1/stream"
    return url + (f"?token={token}" if token else "")


class Session:
    """A synchronous streaming session (websockets' sync client)."""

    def __init__(self, base_url: str, token: str | None = None, **start) -> None:
        self.url, self.start_args = _ws_url(base_url, token), start
        self.resume_token: str | None = None
        self.seq = 0
        self.reconnects = 0  # successful resumes after a lost connection
        self.replay = ReplayBuffer()
        self._open()

    def _open(self) -> None:
        from websockets.exceptions import ConnectionClosed, InvalidHandshake
        from websockets.sync.client import connect

        for attempt in range(RESUME_ATTEMPTS):
            self._connection = ExitStack()  # websockets wants its connection used as a context manager
            try:
                self.ws = self._connection.enter_context(connect(self.url, max_size=2**22))
                self.ws.send(_start_message(**{**self.start_args, "resume_token": self.resume_token}))
                started = _raise_if_error(json.loads(self.ws.recv(timeout=30)))
                break
            except (ServerError, ConnectionClosed, InvalidHandshake, OSError) as err:
                self._connection.close()
                retry = self.resume_token is not None and (not isinstance(err, ServerError) or err.code in RETRY_CODES)
                if not retry or attempt == RESUME_ATTEMPTS - 1:
                    raise
                time.sleep(RESUME_BACKOFF_S * (attempt + 1))
        self.info = started
        self.joints: list[str] = started["joints"]
        self.resume_token = started["resume_token"]

    def _resume(self, pending: int | None) -> StyledFrame | None:
        """Reconnect and send again what the restored snapshot lacks, reading each reply (known
        already, discarded) before the next, as a burst would overrun the server's frame queue.
        The last message is the caller's own (`pending`: its frame's seq): its reply is left to
        the caller, unless the snapshot already holds that frame, whose saved reply is returned."""
        self._connection.close()
        self._open()
        self.reconnects += 1
        missing = self.replay.after(self.info["last_seq"])
        if not missing or missing[-1] is not self.replay.entries[-1]:
            saved = _saved_reply(self.info, pending)
            if saved is None:
                raise ResumeError("the server saved the last message but its reply was lost")
            return saved
        for seq, message in missing[:-1]:  # one at a time: a burst would overrun the session's queue
            self.ws.send(message)
            self._reply(seq)
        self.ws.send(missing[-1][1])
        return None

    def _reply(self, seq: int | None) -> StyledFrame | dict:
        """The reply to a frame (`seq`) or to a control message (None), acting on snapshot
        acknowledgements on the way."""
        while True:
            data = self.ws.recv(timeout=30)
            if isinstance(data, bytes):
                frame = _unpack(data, len(self.joints))
                if seq is not None and frame.seq == seq:
                    return frame
                continue  # a reply the client has already had
            message = _raise_if_error(json.loads(data))
            if message.get("type") == "snapshot":
                self.replay.acknowledged(message["last_seq"])
            elif seq is None:
                return message

    def _call(self, seq: int | None, message: bytes | str) -> StyledFrame | dict:
        """Send one message and return its reply, resuming once if the connection goes."""
        from websockets.exceptions import ConnectionClosed

        self.replay.add(seq, message)
        try:
            self.ws.send(message)
            return self._reply(seq)
        except ConnectionClosed:
            saved = self._resume(seq)
            return saved if saved is not None else self._reply(seq)

    def stylise(self, root: np.ndarray, rotations: np.ndarray) -> StyledFrame:
        """Send one frame and wait for its stylised twin (resuming by itself, see the module)."""
        frame = self._call(self.seq, _pack(self.seq, root, rotations))
        self.seq += 1
        return frame

    def control(self, velocity: tuple[float, float], facing: float, gait: str = "walk") -> StyledFrame:
        """Drive a controller model (LPN-FiLM) one tick: velocity [forward, side] m/s (side > 0 to
        the left), facing yaw in radians (0 = world +Z); returns the synthesised frame."""
        frame = self._call(self.seq, _control_message(self.seq, velocity, facing, gait))
        self.seq += 1
        return frame

    def set_style(self, style: str | None = None, mix: dict[str, float] | None = None, intensity: float = 1.0,
                  transition_frames: int = 0) -> dict:
        return self._call(None, _style_message(style, mix, intensity, transition_frames))

    def reset(self) -> None:
        self._call(None, json.dumps({"type": "reset"}))

    def close(self) -> None:
        try:
            self.ws.send(json.dumps({"type": "end"}))
            self.ws.recv(timeout=5)
        except Exception:  # noqa: BLE001 - closing an already broken socket
            pass
        self._connection.close()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Client:
    """Synchronous REST client plus sessions."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None, timeout: float = 30.0) -> None:
        self.base_url, self.token = base_url.rstrip("/"), token
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout)

    def models(self) -> list[ModelInfo]:
        response = self.http.get("/v1/models")
        response.raise_for_status()
        return [ModelInfo(**m) for m in response.json()]

    def session(self, model: str, style: str | None = None, mix: dict[str, float] | None = None,
                skeleton: str | None = "bandai-namco", bvh_header: str | None = None, fps: float = 30.0,
                intensity: float = 1.0) -> Session:
        return Session(self.base_url, self.token, model=model, style=style, mix=mix, skeleton=skeleton,
                       bvh_header=bvh_header, fps=fps, intensity=intensity)


class AsyncSession:
    """An asyncio streaming session; resumes like `Session`."""

    def __init__(self, base_url: str, token: str | None = None, **start) -> None:
        self.url, self.start_args = _ws_url(base_url, token), start
        self.resume_token: str | None = None
        self.seq = 0
        self.reconnects = 0
        self.replay = ReplayBuffer()

    async def open(self) -> AsyncSession:
        import websockets
        from websockets.exceptions import ConnectionClosed, InvalidHandshake

        for attempt in range(RESUME_ATTEMPTS):
            try:
                self.ws = await websockets.connect(self.url, max_size=2**22)
            except (InvalidHandshake, OSError):
                if self.resume_token is None or attempt == RESUME_ATTEMPTS - 1:
                    raise
                await asyncio.sleep(RESUME_BACKOFF_S * (attempt + 1))
                continue
            try:
                await self.ws.send(_start_message(**{**self.start_args, "resume_token": self.resume_token}))
                started = _raise_if_error(json.loads(await self.ws.recv()))
                break
            except (ServerError, ConnectionClosed) as err:
                await self.ws.close()
                retry = self.resume_token is not None and (not isinstance(err, ServerError) or err.code in RETRY_CODES)
                if not retry or attempt == RESUME_ATTEMPTS - 1:
                    raise
                await asyncio.sleep(RESUME_BACKOFF_S * (attempt + 1))
        self.info, self.joints, self.resume_token = started, started["joints"], started["resume_token"]
        return self

    async def _resume(self, pending: int | None) -> StyledFrame | None:
        await self.ws.close()
        await self.open()
        self.reconnects += 1
        missing = self.replay.after(self.info["last_seq"])
        if not missing or missing[-1] is not self.replay.entries[-1]:
            saved = _saved_reply(self.info, pending)
            if saved is None:
                raise ResumeError("the server saved the last message but its reply was lost")
            return saved
        for seq, message in missing[:-1]:
            await self.ws.send(message)
            await self._reply(seq)
        await self.ws.send(missing[-1][1])
        return None

    async def _reply(self, seq: int | None) -> StyledFrame | dict:
        while True:
            data = await self.ws.recv()
            if isinstance(data, bytes):
                frame = _unpack(data, len(self.joints))
                if seq is not None and frame.seq == seq:
                    return frame
                continue
            message = _raise_if_error(json.loads(data))
            if message.get("type") == "snapshot":
                self.replay.acknowledged(message["last_seq"])
            elif seq is None:
                return message

    async def _call(self, seq: int | None, message: bytes | str) -> StyledFrame | dict:
        from websockets.exceptions import ConnectionClosed

        self.replay.add(seq, message)
        try:
            await self.ws.send(message)
            return await self._reply(seq)
        except ConnectionClosed:
            saved = await self._resume(seq)
            return saved if saved is not None else await self._reply(seq)

    async def stylise(self, root: np.ndarray, rotations: np.ndarray) -> StyledFrame:
        frame = await self._call(self.seq, _pack(self.seq, root, rotations))
        self.seq += 1
        return frame

    async def control(self, velocity: tuple[float, float], facing: float, gait: str = "walk") -> StyledFrame:
        frame = await self._call(self.seq, _control_message(self.seq, velocity, facing, gait))
        self.seq += 1
        return frame

    async def set_style(self, style: str | None = None, mix: dict[str, float] | None = None, intensity: float = 1.0,
                        transition_frames: int = 0) -> dict:
        return await self._call(None, _style_message(style, mix, intensity, transition_frames))

    async def reset(self) -> None:
        await self._call(None, json.dumps({"type": "reset"}))

    async def close(self) -> None:
        try:
            await self.ws.send(json.dumps({"type": "end"}))
            await self.ws.recv()
        except Exception:  # noqa: BLE001
            pass
        await self.ws.close()

    async def __aenter__(self) -> AsyncSession:
        return await self.open()

    async def __aexit__(self, *exc) -> None:
        await self.close()


class AsyncClient:
    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None, timeout: float = 30.0) -> None:
        self.base_url, self.token = base_url.rstrip("/"), token
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.AsyncClient(base_url=self.base_url, headers=headers, timeout=timeout)

    async def models(self) -> list[ModelInfo]:
        response = await self.http.get("/v1/models")
        response.raise_for_status()
        return [ModelInfo(**m) for m in response.json()]

    def session(self, model: str, style: str | None = None, mix: dict[str, float] | None = None,
                skeleton: str | None = "bandai-namco", bvh_header: str | None = None, fps: float = 30.0,
                intensity: float = 1.0) -> AsyncSession:
        return AsyncSession(self.base_url, self.token, model=model, style=style, mix=mix, skeleton=skeleton,
                            bvh_header=bvh_header, fps=fps, intensity=intensity)
