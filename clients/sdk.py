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

Frames travel as binary (docs/protocol.md); a session that loses its connection reconnects
with its resume token by itself and continues where the server's snapshot left off.
"""

from __future__ import annotations

import asyncio
import json
import struct
import time
from contextlib import ExitStack
from dataclasses import dataclass

import httpx
import numpy as np
from pydantic import BaseModel

HEADER = struct.Struct("<IHH")
RESUME_ATTEMPTS = 5  # reconnects racing the server's notice of the dropped connection
RESUME_BACKOFF_S = 0.05


class ModelInfo(BaseModel):
    name: str
    styles: list[str]
    joints: list[str]


class ServerError(RuntimeError):
    """A typed error message from the server."""

    def __init__(self, code: str, message: str, seq: int | None = None) -> None:
        super().__init__(f"{code}: {message}")
        self.code, self.message, self.seq = code, message, seq


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
    return json.dumps(msg)


def _style_message(style: str | None, mix: dict[str, float] | None, intensity: float, transition_frames: int) -> str:
    msg = {"type": "style", "intensity": intensity, "transition_frames": transition_frames}
    msg.update({"mix": mix} if mix is not None else {"style": style})
    return json.dumps(msg)


def _pack(seq: int, root: np.ndarray, rotations: np.ndarray) -> bytes:
    return HEADER.pack(seq & 0xFFFFFFFF, 1, 0) + np.concatenate([np.ravel(root), np.ravel(rotations)]).astype("<f4").tobytes()


def _unpack(data: bytes, joints: int) -> StyledFrame:
    seq, _, dropped = HEADER.unpack_from(data)
    values = np.frombuffer(data, "<f4", offset=HEADER.size).astype(np.float64)
    return StyledFrame(seq, values[:3], values[3:].reshape(joints, 4), dropped)


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
        self._open()

    def _open(self) -> None:
        from websockets.sync.client import connect

        for attempt in range(RESUME_ATTEMPTS):
            self._connection = ExitStack()  # websockets wants its connection used as a context manager
            self.ws = self._connection.enter_context(connect(self.url, max_size=2**22))
            self.ws.send(_start_message(**{**self.start_args, "resume_token": self.resume_token}))
            try:
                started = _raise_if_error(json.loads(self.ws.recv(timeout=30)))
                break
            except ServerError as err:  # the server may not have seen the old connection go yet
                self._connection.close()
                if err.code != "session_in_use" or attempt == RESUME_ATTEMPTS - 1:
                    raise
                time.sleep(RESUME_BACKOFF_S * (attempt + 1))
        self.info = started
        self.joints: list[str] = started["joints"]
        self.resume_token = started["resume_token"]

    def stylise(self, root: np.ndarray, rotations: np.ndarray) -> StyledFrame:
        """Send one frame and wait for its stylised twin. Reconnects and resumes once if the
        connection drops (the frame is sent again)."""
        from websockets.exceptions import ConnectionClosed

        for attempt in (0, 1):
            try:
                self.ws.send(_pack(self.seq, root, rotations))
                while True:
                    data = self.ws.recv(timeout=30)
                    if isinstance(data, bytes):
                        frame = _unpack(data, len(self.joints))
                        self.seq += 1
                        return frame
                    _raise_if_error(json.loads(data))
            except ConnectionClosed:
                if attempt:
                    raise
                self._connection.close()
                self._open()
        raise AssertionError("unreachable")

    def set_style(self, style: str | None = None, mix: dict[str, float] | None = None, intensity: float = 1.0,
                  transition_frames: int = 0) -> dict:
        self.ws.send(_style_message(style, mix, intensity, transition_frames))
        return _raise_if_error(json.loads(self.ws.recv(timeout=30)))

    def reset(self) -> None:
        self.ws.send(json.dumps({"type": "reset"}))
        _raise_if_error(json.loads(self.ws.recv(timeout=30)))

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
    """An asyncio streaming session."""

    def __init__(self, base_url: str, token: str | None = None, **start) -> None:
        self.url, self.start_args = _ws_url(base_url, token), start
        self.resume_token: str | None = None
        self.seq = 0

    async def open(self) -> AsyncSession:
        import websockets

        for attempt in range(RESUME_ATTEMPTS):
            self.ws = await websockets.connect(self.url, max_size=2**22)
            await self.ws.send(_start_message(**{**self.start_args, "resume_token": self.resume_token}))
            try:
                started = _raise_if_error(json.loads(await self.ws.recv()))
                break
            except ServerError as err:  # the server may not have seen the old connection go yet
                await self.ws.close()
                if err.code != "session_in_use" or attempt == RESUME_ATTEMPTS - 1:
                    raise
                await asyncio.sleep(RESUME_BACKOFF_S * (attempt + 1))
        self.info, self.joints, self.resume_token = started, started["joints"], started["resume_token"]
        return self

    async def stylise(self, root: np.ndarray, rotations: np.ndarray) -> StyledFrame:
        from websockets.exceptions import ConnectionClosed

        for attempt in (0, 1):
            try:
                await self.ws.send(_pack(self.seq, root, rotations))
                while True:
                    data = await self.ws.recv()
                    if isinstance(data, bytes):
                        self.seq += 1
                        return _unpack(data, len(self.joints))
                    _raise_if_error(json.loads(data))
            except ConnectionClosed:
                if attempt:
                    raise
                await self.open()
        raise AssertionError("unreachable")

    async def set_style(self, style: str | None = None, mix: dict[str, float] | None = None, intensity: float = 1.0,
                        transition_frames: int = 0) -> dict:
        await self.ws.send(_style_message(style, mix, intensity, transition_frames))
        return _raise_if_error(json.loads(await self.ws.recv()))

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
