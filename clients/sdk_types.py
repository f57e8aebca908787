"""What the SDK hands its callers: stylised frames, REST resources, reconnect reports, typed errors.

Plain dataclasses, no pydantic: the SDK installs with numpy, httpx and websockets only. REST
resources are read with `from_json`, which keeps the fields this SDK knows and ignores the rest,
so an older SDK keeps working against a newer server that adds fields.

Every error the SDK raises is a `StylestreamError`. The connection-shaped ones also derive from
the built-in `ConnectionError` / `TimeoutError` (both `OSError`s), so code that already catches
those, such as the CLI's one-line user errors, handles them unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Literal, TypeVar

import numpy as np

T = TypeVar("T")


# ---- errors ------------------------------------------------------------------------------------


class StylestreamError(RuntimeError):
    """Base of every error the SDK raises."""


class ServerError(StylestreamError):
    """A typed error from the server: a stream `error` message (docs/protocol.md#errors), or a REST
    error body `{"code", "message"}` with its HTTP `status` (None on the stream)."""

    def __init__(
        self,
        code: str,
        message: str,
        seq: int | None = None,
        status: int | None = None,
        retry_after: float | None = None,
        character: int | None = None,  # in a crowd: the character it concerns
    ) -> None:
        super().__init__(f"{code}: {message}" if character is None else f"{code} (character {character}): {message}")
        self.code, self.message, self.seq = code, message, seq
        self.status, self.retry_after, self.character = status, retry_after, character


class ResumeError(StylestreamError):
    """The session cannot continue exactly: the server's snapshot and the messages this client
    still holds do not meet (the replay buffer overflowed while the server stored no snapshot,
    or a reply was lost after the server had saved its frame)."""


class ConnectFailed(StylestreamError, ConnectionError):
    """No session could be opened: the server refused the connection, the handshake failed, or
    no `started` came within the timeout."""


class ConnectionLost(StylestreamError, ConnectionError):
    """The connection went and neither a resume nor a fresh session succeeded before the
    session's `reconnect_timeout` ran out."""


class ReplyTimeout(StylestreamError, TimeoutError):
    """No reply within the caller's timeout. The session stays usable: a reply that comes late
    to a call that gave up is discarded."""


class FrameDropped(StylestreamError):
    """The server dropped this frame (its session queue was full: backpressure) and so never
    answered it. Only a caller that pipelines more frames than the server queues meets it."""


class NothingInFlight(StylestreamError):
    """`receive()` with no pipelined frame awaiting its reply: it would wait forever."""


class JobFailed(StylestreamError):
    """A background job (`wait_job`) ended in `failed`; `job` holds the server's account."""

    def __init__(self, job: JobInfo) -> None:
        super().__init__(f"job {job.id} failed: {job.message}")
        self.job = job


class JobTimeout(StylestreamError, TimeoutError):
    """`wait_job` gave up before the job finished (the job itself goes on)."""


# ---- stream ------------------------------------------------------------------------------------


@dataclass
class StyledFrame:
    seq: int
    root: np.ndarray  # (3,)
    rotations: np.ndarray  # (J, 4)
    dropped: int  # frames the server dropped before this one (backpressure)
    notices: tuple[ServerError, ...] = ()  # e.g. `style_deleted`, sent before this frame's reply
    faded: float = 0.0  # how far the frame faded toward the input (unseen content); 0 for a core pipeline


@dataclass(frozen=True)
class Reconnect:
    """How a session came back after its connection went; given to `on_reconnect` and kept as
    `session.last_reconnect`.

    `resumed`: the server restored the session from its snapshot and the SDK replayed what the
    snapshot lacked, so outputs equal an uninterrupted run's. `new_session`: the server no longer
    knew the resume token (restarted without a shared store, or the snapshot expired), so a fresh
    session was opened with the same settings and current style; the model's state started over."""

    kind: Literal["resumed", "new_session"]
    attempts: int  # connection attempts it took
    seconds: float  # from noticing the loss to the new `started`
    session_id: str
    last_seq: int | None  # resumed: the last frame the restored state had seen
    replayed: int  # messages sent again
    lost: tuple[int, ...]  # pipelined frames whose replies went with the connection (the state has them)
    cause: str  # why the connection went


@dataclass(frozen=True)
class CrowdReconnect:
    """How a crowd came back after its connection went (`crowd.last_reconnect`): its characters
    resumed by their tokens and the ticks their stored state lacked were sent again, so replies go
    on as an uninterrupted crowd's; characters in `fresh` had been forgotten by the server (store
    restarted or snapshot expired) and started over with their first settings."""

    attempts: int
    seconds: float
    last_seq: int | None  # the last tick the resumed characters' stored state had answered
    replayed: int  # ticks sent again (the one waiting for its reply included)
    fresh: list[int]
    cause: str


# ---- REST resources --------------------------------------------------------------------------


def from_json(cls: type[T], data: dict[str, Any]) -> T:
    """`cls` from a JSON object, keeping only the fields `cls` declares."""
    names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    return cls(**{k: v for k, v in data.items() if k in names})


@dataclass(frozen=True)
class ModelInfo:
    name: str
    styles: list[str]
    joints: list[str]
    controllable: bool = False  # sessions may send `control` ticks (Session.control) instead of frames
    pipelines: list[str] = field(
        default_factory=lambda: ["full"]
    )  # what a session may ask for in `pipeline` ("full", "core")


@dataclass(frozen=True)
class StyleInfo:
    id: str  # '<model>.<name>'
    name: str
    model: str
    kind: Literal["trained", "uploaded"]
    status: Literal["ready", "training", "failed"]
    created: float | None = None
    job_id: str | None = None
    message: str | None = None
    frames: int | None = None
    source: str | None = None
    skeleton: str | None = None
    fine_tune: dict[str, Any] | None = None


@dataclass(frozen=True)
class JobInfo:
    id: str
    kind: str
    status: Literal["queued", "running", "done", "failed"]
    progress: float = 0.0  # 0..1
    message: str = ""
    target: str | None = None  # the style id the job produces
    created: float | None = None
    started: float | None = None
    finished: float | None = None
    result: dict[str, Any] | None = None


@dataclass(frozen=True)
class AddedStyle:
    """One model's outcome of `add_style`: the style (ready, or still training when the wait ran
    out), or why that model refused it; with the seconds from the upload until the style could
    be streamed (`live_s`) and until its job finished (`done_s`)."""

    model: str
    style: StyleInfo | None = None
    error: StylestreamError | None = None
    live_s: float | None = None
    done_s: float | None = None


@dataclass(frozen=True)
class Upload:
    """`POST /v1/styles`' answer: the new style and, when fine-tuning was asked for, its job."""

    style: StyleInfo
    job: JobInfo | None = None
    created: bool = field(default=False)  # 201: the style was usable at once (LPN-FiLM); 202: a job makes it

    @classmethod
    def from_json(cls, data: dict[str, Any], status: int) -> Upload:
        job = data.get("job")
        return cls(from_json(StyleInfo, data["style"]), from_json(JobInfo, job) if job else None, status == 201)
