"""Python SDK for the stylestream service: REST calls and streaming sessions, sync and asyncio.

    from clients.sdk import Client

    with Client("http://127.0.0.1:8000", timeout=10) as client:
        print(client.models(), client.styles(model="lti"))
        with client.session(model="lti", style="elderly") as s:
            for root, rotations in frames:               # root (3,), rotations (J, 4) xyzw
                out = s.stylise(root, rotations)          # one frame in, one frame out
            s.set_style("exhausted", transition_frames=30)

    # a game loop: send frame t without waiting for t-1's reply, take replies as they come
    with client.session(model="lti", style="elderly", max_in_flight=4) as s:
        for root, rotations in frames:
            s.send(root, rotations)
            for out in s.poll():                          # replies that have arrived, in order
                draw(out)

    # a crowd: many characters on one connection, one binary message per tick each way
    with client.crowd([Character(i, "lti", "elderly") for i in range(100)], fps=60) as crowd:
        for roots, rotations in ticks:                    # (100, 3), (100, J, 4)
            out = crowd.tick(range(100), roots, rotations)
            out_roots, out_rotations = out.arrays()

    # asyncio: the same calls, awaited
    async with AsyncClient("http://127.0.0.1:8000") as client:
        async with client.session(model="lti", style="elderly") as s:
            out = await s.stylise(root, rotations)

Installs with numpy, httpx and websockets only: nothing here imports the server (`models`,
`service`) or its dependencies. Frames travel as binary (docs/protocol.md).

A session that loses its connection (a dropped network, a replica drained with 1012, killed or
restarted) reconnects by itself, backing off until `reconnect_timeout`, to whichever replica the
address leads to. It resumes with its token and replays what the server's last stored snapshot
lacks (the frames and style changes sent since, kept in a bounded `ReplayBuffer` trimmed by the
server's snapshot acknowledgements), so the outputs equal an uninterrupted run's; when the server
no longer knows the token it opens a fresh session with the same settings. Either way it says so:
`on_reconnect(Reconnect)`, `session.last_reconnect`, `session.reconnects` / `session.new_sessions`.

The protocol is written once (`sdk_session`, `sdk_rest`); `Session`/`Client` and
`AsyncSession`/`AsyncClient` are thin faces that run it with sync or asyncio I/O (`sdk_io`).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Sequence
from types import EllipsisType
from typing import Any

import httpx
import numpy as np

from . import sdk_rest as rest
from .sdk_crowd import AsyncCrowd, Character, Crowd, CrowdCore, CrowdFrames
from .sdk_io import AsyncIO, SyncIO, run_async, run_sync
from .sdk_session import SessionCore
from .sdk_types import (
    AddedStyle,
    ConnectFailed,
    ConnectionLost,
    FrameDropped,
    JobFailed,
    JobInfo,
    JobTimeout,
    ModelInfo,
    NothingInFlight,
    Reconnect,
    ReplyTimeout,
    ResumeError,
    ServerError,
    StyledFrame,
    StyleInfo,
    StylestreamError,
    Upload,
)
from .sdk_wire import HEADER, ReplayBuffer, StartSettings, auth_headers, ws_url
from .sdk_wire import pack as _pack

__all__ = [
    "AddedStyle",
    "AsyncClient",
    "AsyncCrowd",
    "AsyncSession",
    "Character",
    "Client",
    "Crowd",
    "CrowdFrames",
    "ConnectFailed",
    "ConnectionLost",
    "FrameDropped",
    "HEADER",
    "JobFailed",
    "JobInfo",
    "JobTimeout",
    "ModelInfo",
    "NothingInFlight",
    "Reconnect",
    "ReplayBuffer",
    "ReplyTimeout",
    "ResumeError",
    "ServerError",
    "Session",
    "StyleInfo",
    "StyledFrame",
    "StylestreamError",
    "Upload",
    "_pack",
]

TIMEOUT_S = 30.0  # each REST request, opening a session, each reply
RECONNECT_TIMEOUT_S = 60.0  # how long a session keeps trying to come back after losing its connection
MAX_IN_FLIGHT = 8  # pipelined frames in flight: the server's default session queue, so none is dropped
Default = float | None | EllipsisType  # `...`: the client's setting


class _SessionState:
    """What a session shows, sync or asyncio alike."""

    core: SessionCore

    @property
    def info(self) -> dict[str, Any]:
        """The server's latest `started` message (docs/protocol.md#opening-a-session)."""
        return self.core.info

    @property
    def joints(self) -> list[str]:
        return self.core.joints

    @property
    def session_id(self) -> str | None:
        return self.core.info.get("session_id")

    @property
    def resume_token(self) -> str | None:
        return self.core.resume_token

    @property
    def seq(self) -> int:
        """The sequence number the next frame gets."""
        return self.core.seq

    @property
    def reconnects(self) -> int:
        """Resumes after a lost connection."""
        return self.core.reconnects

    @property
    def new_sessions(self) -> int:
        """Fresh sessions opened because the server no longer knew the resume token."""
        return self.core.new_sessions

    @property
    def last_reconnect(self) -> Reconnect | None:
        return self.core.last_reconnect

    @property
    def notices(self) -> list[ServerError]:
        """Errors from the server that answer nothing this session sent."""
        return self.core.notices

    @property
    def replay(self) -> ReplayBuffer:
        return self.core.replay

    @property
    def in_flight(self) -> int:
        """Pipelined frames whose replies have not been taken (`receive`, `poll`)."""
        return self.core.in_flight()


def _core(
    base_url: str,
    token: str | None,
    timeout: float | None,
    reconnect_timeout: float | None,
    max_in_flight: int,
    on_reconnect: Callable[[Reconnect], None] | None,
    **start: Any,
) -> SessionCore:
    return SessionCore(
        ws_url(base_url),
        StartSettings(**start),
        headers=auth_headers(token),
        timeout=timeout,
        reconnect_timeout=reconnect_timeout,
        max_in_flight=max_in_flight,
        on_reconnect=on_reconnect,
    )


class Session(_SessionState):
    """A synchronous streaming session (websockets' sync client); opened on creation."""

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        *,
        timeout: float | None = TIMEOUT_S,
        reconnect_timeout: float | None = RECONNECT_TIMEOUT_S,
        max_in_flight: int = MAX_IN_FLIGHT,
        on_reconnect: Callable[[Reconnect], None] | None = None,
        **start: Any,
    ) -> None:
        self.core = _core(base_url, token, timeout, reconnect_timeout, max_in_flight, on_reconnect, **start)
        self._io = SyncIO()
        run_sync(self.core.open(), self._io)

    @property
    def ws(self) -> Any:
        """The current WebSocket connection (websockets' sync `ClientConnection`)."""
        return self._io.ws

    def stylise(self, root: np.ndarray, rotations: np.ndarray) -> StyledFrame:
        """Send one frame and wait for its stylised twin."""
        return run_sync(self.core.stylise(root, rotations), self._io)

    def control(self, velocity: tuple[float, float], facing: float, gait: str = "walk") -> StyledFrame:
        """Drive a controller model (LPN-FiLM) one tick: velocity [forward, side] m/s (side > 0 to
        the left), facing yaw in radians (0 = world +Z); returns the synthesised frame."""
        return run_sync(self.core.control(velocity, facing, gait), self._io)

    def set_style(
        self,
        style: str | None = None,
        mix: dict[str, float] | None = None,
        intensity: float = 1.0,
        transition_frames: int = 0,
    ) -> dict[str, Any]:
        return run_sync(self.core.set_style(style, mix, intensity, transition_frames), self._io)

    def reset(self) -> None:
        run_sync(self.core.reset(), self._io)

    def send(self, root: np.ndarray, rotations: np.ndarray) -> int:
        """Pipelined: send a frame without waiting for its reply (only, with `max_in_flight`
        frames unanswered, for the oldest); returns its seq. Take replies with `receive`/`poll`."""
        return run_sync(self.core.send(root, rotations), self._io)

    def send_control(self, velocity: tuple[float, float], facing: float, gait: str = "walk") -> int:
        """`control`, pipelined like `send`."""
        return run_sync(self.core.send_control(velocity, facing, gait), self._io)

    def receive(self, timeout: Default = ...) -> StyledFrame:
        """The next pipelined reply, in send order, waiting up to `timeout` (default: the session's)."""
        return run_sync(self.core.receive(self.core.timeout if timeout is ... else timeout), self._io)

    def poll(self) -> list[StyledFrame]:
        """The pipelined replies that have arrived, in order, without waiting."""
        return run_sync(self.core.poll(), self._io)

    def close(self) -> None:
        run_sync(self.core.close(), self._io)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncSession(_SessionState):
    """An asyncio streaming session; `await session.open()` or `async with`."""

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        *,
        timeout: float | None = TIMEOUT_S,
        reconnect_timeout: float | None = RECONNECT_TIMEOUT_S,
        max_in_flight: int = MAX_IN_FLIGHT,
        on_reconnect: Callable[[Reconnect], None] | None = None,
        **start: Any,
    ) -> None:
        self.core = _core(base_url, token, timeout, reconnect_timeout, max_in_flight, on_reconnect, **start)
        self._io = AsyncIO()

    @property
    def ws(self) -> Any:
        """The current WebSocket connection (websockets' asyncio `ClientConnection`)."""
        return self._io.ws

    async def open(self) -> AsyncSession:
        await run_async(self.core.open(), self._io)
        return self

    async def stylise(self, root: np.ndarray, rotations: np.ndarray) -> StyledFrame:
        return await run_async(self.core.stylise(root, rotations), self._io)

    async def control(self, velocity: tuple[float, float], facing: float, gait: str = "walk") -> StyledFrame:
        return await run_async(self.core.control(velocity, facing, gait), self._io)

    async def set_style(
        self,
        style: str | None = None,
        mix: dict[str, float] | None = None,
        intensity: float = 1.0,
        transition_frames: int = 0,
    ) -> dict[str, Any]:
        return await run_async(self.core.set_style(style, mix, intensity, transition_frames), self._io)

    async def reset(self) -> None:
        await run_async(self.core.reset(), self._io)

    async def send(self, root: np.ndarray, rotations: np.ndarray) -> int:
        return await run_async(self.core.send(root, rotations), self._io)

    async def send_control(self, velocity: tuple[float, float], facing: float, gait: str = "walk") -> int:
        return await run_async(self.core.send_control(velocity, facing, gait), self._io)

    async def receive(self, timeout: Default = ...) -> StyledFrame:
        return await run_async(self.core.receive(self.core.timeout if timeout is ... else timeout), self._io)

    async def poll(self) -> list[StyledFrame]:
        return await run_async(self.core.poll(), self._io)

    async def close(self) -> None:
        await run_async(self.core.close(), self._io)

    async def __aenter__(self) -> AsyncSession:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class _ClientBase:
    def __init__(
        self, base_url: str, token: str | None, timeout: float | None, reconnect_timeout: float | None
    ) -> None:
        self.base_url, self.token = base_url.rstrip("/"), token
        self.timeout, self.reconnect_timeout = timeout, reconnect_timeout
        self.headers = {"Authorization": f"Bearer {token}"} if token else {}

    def _session_args(
        self,
        model: str,
        style: str | None,
        mix: dict[str, float] | None,
        skeleton: str | None,
        bvh_header: str | None,
        fps: float,
        intensity: float,
        timeout: Default,
        reconnect_timeout: Default,
        max_in_flight: int,
        on_reconnect: Callable[[Reconnect], None] | None,
        pipeline: str,
    ) -> dict[str, Any]:
        return {
            "base_url": self.base_url,
            "token": self.token,
            "model": model,
            "style": style,
            "mix": mix,
            "skeleton": skeleton,
            "bvh_header": bvh_header,
            "fps": fps,
            "intensity": intensity,
            "pipeline": pipeline,
            "timeout": self.timeout if timeout is ... else timeout,
            "reconnect_timeout": self.reconnect_timeout if reconnect_timeout is ... else reconnect_timeout,
            "max_in_flight": max_in_flight,
            "on_reconnect": on_reconnect,
        }

    def _crowd_core(
        self, characters: Sequence[Character], fps: float, timeout: Default, reconnect_timeout: Default
    ) -> CrowdCore:
        url = self.base_url.replace("http", "ws", 1) + "/v1/stream"
        return CrowdCore(
            url,
            self.headers,
            characters,
            fps,
            self.timeout if timeout is ... else timeout,
            self.reconnect_timeout if reconnect_timeout is ... else reconnect_timeout,
        )


class Client(_ClientBase):
    """Synchronous REST client plus sessions. `timeout` (seconds, None: no limit) bounds each REST
    request, opening a session and each reply; `reconnect_timeout` how long a session keeps trying
    to come back. `close()` (or `with`) closes the HTTP client and the sessions still open."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        token: str | None = None,
        timeout: float | None = TIMEOUT_S,
        reconnect_timeout: float | None = RECONNECT_TIMEOUT_S,
    ) -> None:
        super().__init__(base_url, token, timeout, reconnect_timeout)
        self.http = httpx.Client(base_url=self.base_url, headers=self.headers, timeout=timeout)
        self._io = SyncIO(self.http)
        self._sessions: weakref.WeakSet[Session] = weakref.WeakSet()

    def models(self) -> list[ModelInfo]:
        return run_sync(rest.models(), self._io)

    def styles(self, model: str | None = None) -> list[StyleInfo]:
        """Every style (trained and uploaded), or one model's."""
        return run_sync(rest.styles(model), self._io)

    def style(self, style_id: str) -> StyleInfo:
        return run_sync(rest.style(style_id), self._io)

    def upload_style(
        self,
        name: str,
        *,
        model: str = "lti",
        bvh: rest.Bvh | None = None,
        frames: tuple[np.ndarray, np.ndarray] | None = None,
        fps: float = 30.0,
        fine_tune: bool = False,
    ) -> Upload:
        """A clip as a new style: `bvh` (text, bytes, or a path) or `frames` (root (F, 3), rotations
        (F, 22, 4) xyzw on the model skeleton, at `fps`). LTI needs `fine_tune=True` and answers with
        a job (`wait_job`); LPN-FiLM's style is usable at once (`Upload.created`)."""
        return run_sync(rest.upload_style(name, model, bvh, frames, fps, fine_tune), self._io)

    def delete_style(self, style_id: str) -> None:
        run_sync(rest.delete_style(style_id), self._io)

    def add_style(
        self,
        name: str,
        *,
        models: Sequence[str] | None = None,
        bvh: rest.Bvh | None = None,
        frames: tuple[np.ndarray, np.ndarray] | None = None,
        fps: float = 30.0,
        fine_tune: bool = True,
        progress: Callable[[str, JobInfo], None] | None = None,
        timeout: float | None = None,
        poll_interval: float = 0.25,
    ) -> dict[str, AddedStyle]:
        """One clip as style `name` on each of `models` (default: every model the server has),
        every job followed to its end (`progress(model, job)` on each change; `timeout` stops the
        waiting, not the jobs). A model that refuses the clip is reported in its `AddedStyle.error`."""
        names = None if models is None else list(models)
        steps = rest.add_style(name, names, bvh, frames, fps, fine_tune, progress, timeout, poll_interval)
        return run_sync(steps, self._io)

    def job(self, job_id: str) -> JobInfo:
        return run_sync(rest.job(job_id), self._io)

    def wait_job(
        self,
        job_id: str,
        progress: Callable[[JobInfo], None] | None = None,
        timeout: float | None = None,
        poll_interval: float = 0.25,
    ) -> JobInfo:
        """Wait for a job to finish: returns it done, raises `JobFailed` or `JobTimeout`;
        `progress(job)` is called on every change."""
        return run_sync(rest.wait_job(job_id, progress, timeout, poll_interval), self._io)

    def session(
        self,
        model: str,
        style: str | None = None,
        mix: dict[str, float] | None = None,
        skeleton: str | None = "bandai-namco",
        bvh_header: str | None = None,
        fps: float = 30.0,
        intensity: float = 1.0,
        *,
        timeout: Default = ...,
        reconnect_timeout: Default = ...,
        max_in_flight: int = MAX_IN_FLIGHT,
        on_reconnect: Callable[[Reconnect], None] | None = None,
        pipeline: str = "full",
    ) -> Session:
        """Open a streaming session (timeouts default to the client's)."""
        session = Session(
            **self._session_args(
                model,
                style,
                mix,
                skeleton,
                bvh_header,
                fps,
                intensity,
                timeout,
                reconnect_timeout,
                max_in_flight,
                on_reconnect,
                pipeline,
            )
        )
        self._sessions.add(session)
        return session

    def crowd(
        self,
        characters: Sequence[Character],
        fps: float = 30.0,
        *,
        timeout: Default = ...,
        reconnect_timeout: Default = ...,
    ) -> Crowd:
        """Open a crowd: many characters on one connection, one binary message per tick each way
        (protocol v1.1). Characters the server refuses are in the crowd's `errors`. If the
        connection goes, `tick` brings the crowd back by itself until `reconnect_timeout` (0: not)."""
        return Crowd(self._crowd_core(characters, fps, timeout, reconnect_timeout))

    def close(self) -> None:
        for session in list(self._sessions):
            session.close()
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncClient(_ClientBase):
    """`Client` for asyncio."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        token: str | None = None,
        timeout: float | None = TIMEOUT_S,
        reconnect_timeout: float | None = RECONNECT_TIMEOUT_S,
    ) -> None:
        super().__init__(base_url, token, timeout, reconnect_timeout)
        self.http = httpx.AsyncClient(base_url=self.base_url, headers=self.headers, timeout=timeout)
        self._io = AsyncIO(self.http)
        self._sessions: weakref.WeakSet[AsyncSession] = weakref.WeakSet()

    async def models(self) -> list[ModelInfo]:
        return await run_async(rest.models(), self._io)

    async def styles(self, model: str | None = None) -> list[StyleInfo]:
        return await run_async(rest.styles(model), self._io)

    async def style(self, style_id: str) -> StyleInfo:
        return await run_async(rest.style(style_id), self._io)

    async def upload_style(
        self,
        name: str,
        *,
        model: str = "lti",
        bvh: rest.Bvh | None = None,
        frames: tuple[np.ndarray, np.ndarray] | None = None,
        fps: float = 30.0,
        fine_tune: bool = False,
    ) -> Upload:
        return await run_async(rest.upload_style(name, model, bvh, frames, fps, fine_tune), self._io)

    async def delete_style(self, style_id: str) -> None:
        await run_async(rest.delete_style(style_id), self._io)

    async def add_style(
        self,
        name: str,
        *,
        models: Sequence[str] | None = None,
        bvh: rest.Bvh | None = None,
        frames: tuple[np.ndarray, np.ndarray] | None = None,
        fps: float = 30.0,
        fine_tune: bool = True,
        progress: Callable[[str, JobInfo], None] | None = None,
        timeout: float | None = None,
        poll_interval: float = 0.25,
    ) -> dict[str, AddedStyle]:
        names = None if models is None else list(models)
        steps = rest.add_style(name, names, bvh, frames, fps, fine_tune, progress, timeout, poll_interval)
        return await run_async(steps, self._io)

    async def job(self, job_id: str) -> JobInfo:
        return await run_async(rest.job(job_id), self._io)

    async def wait_job(
        self,
        job_id: str,
        progress: Callable[[JobInfo], None] | None = None,
        timeout: float | None = None,
        poll_interval: float = 0.25,
    ) -> JobInfo:
        return await run_async(rest.wait_job(job_id, progress, timeout, poll_interval), self._io)

    def session(
        self,
        model: str,
        style: str | None = None,
        mix: dict[str, float] | None = None,
        skeleton: str | None = "bandai-namco",
        bvh_header: str | None = None,
        fps: float = 30.0,
        intensity: float = 1.0,
        *,
        timeout: Default = ...,
        reconnect_timeout: Default = ...,
        max_in_flight: int = MAX_IN_FLIGHT,
        on_reconnect: Callable[[Reconnect], None] | None = None,
        pipeline: str = "full",
    ) -> AsyncSession:
        """A session to open with `async with` or `await session.open()`."""
        session = AsyncSession(
            **self._session_args(
                model,
                style,
                mix,
                skeleton,
                bvh_header,
                fps,
                intensity,
                timeout,
                reconnect_timeout,
                max_in_flight,
                on_reconnect,
                pipeline,
            )
        )
        self._sessions.add(session)
        return session

    async def crowd(
        self,
        characters: Sequence[Character],
        fps: float = 30.0,
        *,
        timeout: Default = ...,
        reconnect_timeout: Default = ...,
    ) -> AsyncCrowd:
        """`Client.crowd` for asyncio."""
        return await AsyncCrowd(self._crowd_core(characters, fps, timeout, reconnect_timeout)).open()

    async def close(self) -> None:
        for session in list(self._sessions):
            if session.core.connected:
                await session.close()
        await self.http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
