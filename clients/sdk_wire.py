"""The stream's messages as bytes and JSON (docs/protocol.md), and the replay buffer that makes a
resume exact. No I/O here: `sdk_session` decides what to send, `sdk_io` sends it."""

from __future__ import annotations

import json
import struct
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .sdk_types import ResumeError, ServerError, StyledFrame

HEADER = struct.Struct("<IHH")  # seq, kind (1 = frame), dropped
MAX_MESSAGE = 2**22  # the largest reply accepted (a big custom rig's JSON frame fits)
REPLAY_LIMIT = 1024  # messages kept for replay; a server acknowledges a snapshot every 30 frames by default
ACKS = {"style": "style_set", "reset": "reset_done"}  # control message -> the reply that answers it

Message = bytes | str


@dataclass(frozen=True)
class StartSettings:
    """What a session is opened with; a fresh session after a lost one is opened with these too
    (the style fields follow the last acknowledged `set_style`)."""

    model: str
    style: str | None = None
    mix: dict[str, float] | None = None
    skeleton: str | None = "bandai-namco"
    bvh_header: str | None = None
    fps: float = 30.0
    intensity: float = 1.0
    pipeline: str = "full"  # "core": the method's published core alone (docs/protocol.md, Pipelines)

    def restyled(self, style: str | None, mix: dict[str, float] | None, intensity: float) -> StartSettings:
        return replace(self, style=style, mix=mix, intensity=intensity)


def start_message(settings: StartSettings, resume_token: str | None) -> str:
    msg: dict[str, Any] = {
        "type": "start",
        "model": settings.model,
        "fps": settings.fps,
        "encoding": "binary-faded",  # binary replies that end in the frame's `faded`
        "intensity": settings.intensity,
    }
    if settings.pipeline != "full":
        msg["pipeline"] = settings.pipeline
    if settings.mix is not None:
        msg["mix"] = settings.mix
    else:
        msg["style"] = settings.style
    if settings.bvh_header is not None:
        msg["bvh_header"] = settings.bvh_header
    elif settings.skeleton is not None:
        msg["skeleton"] = settings.skeleton
    if resume_token:
        msg["resume_token"] = resume_token
    msg["snapshot_acks"] = True  # the replay buffer forgets what a stored snapshot covers
    return json.dumps(msg)


def style_message(style: str | None, mix: dict[str, float] | None, intensity: float, transition_frames: int) -> str:
    msg: dict[str, Any] = {"type": "style", "intensity": intensity, "transition_frames": transition_frames}
    msg.update({"mix": mix} if mix is not None else {"style": style})
    return json.dumps(msg)


def control_message(seq: int, velocity: tuple[float, float], facing: float, gait: str) -> str:
    return json.dumps(
        {
            "type": "control",
            "seq": seq,
            "velocity": [float(velocity[0]), float(velocity[1])],
            "facing": float(facing),
            "gait": gait,
        }
    )


RESET = json.dumps({"type": "reset"})
END = json.dumps({"type": "end"})


def ack_for(seq: int | None, message: Message) -> str | None:
    """The reply type that answers `message`: None for frames and control ticks (answered by a
    frame with their `seq`), `style_set` / `reset_done` for control messages."""
    if seq is not None or isinstance(message, bytes):
        return None
    return ACKS.get(json.loads(message)["type"])


def pack(seq: int, root: np.ndarray, rotations: np.ndarray) -> bytes:
    return (
        HEADER.pack(seq & 0xFFFFFFFF, 1, 0)
        + np.concatenate([np.ravel(root), np.ravel(rotations)]).astype("<f4").tobytes()
    )


def unpack(data: bytes, joints: int) -> StyledFrame:
    """A `binary-faded` frame reply: root, rotations, then `faded` (absent from a plain `binary` one)."""
    seq, _, dropped = HEADER.unpack_from(data)
    values = np.frombuffer(data, "<f4", offset=HEADER.size).astype(np.float64)
    end = 3 + 4 * joints
    faded = float(values[end]) if len(values) > end else 0.0
    return StyledFrame(seq, values[:3], values[3:end].reshape(joints, 4), dropped, faded=faded)


def json_frame(message: dict[str, Any]) -> StyledFrame:
    """A JSON frame reply (or `started.last_frame`), rounded to float32 like a binary one."""
    return StyledFrame(
        message["seq"],
        np.asarray(message["root"], np.float32).astype(np.float64),
        np.asarray(message["rotations"], np.float32).astype(np.float64),
        message.get("dropped", 0),
        faded=float(message.get("faded", 0.0)),
    )


def saved_reply(started: dict[str, Any], seq: int | None) -> StyledFrame | None:
    """The reply to frame `seq` as the server saved it with the snapshot (`started.last_frame`):
    the server had processed the frame when the connection went, but its reply never arrived."""
    last = started.get("last_frame")
    if seq is None or last is None or last["seq"] != seq:
        return None
    return json_frame(last)


def server_error(message: dict[str, Any]) -> ServerError:
    return ServerError(message.get("code", "error"), message.get("message", ""), message.get("seq"))


def ws_url(base_url: str) -> str:
    return base_url.rstrip("/").replace("http://", "ws://", 1).replace("https://", "wss://", 1) + "/v1/stream"


def auth_headers(token: str | None) -> dict[str, str]:
    """The token as `Authorization: Bearer`, never in the URL (where proxies and logs keep it)."""
    return {"Authorization": f"Bearer {token}"} if token else {}


class ReplayBuffer:
    """The messages sent since the last snapshot the server acknowledged, in order, so a resumed
    session can be brought up to date. Frames are binary messages with their sequence number;
    control messages (style, reset) are text. Replaying a control message the snapshot already
    holds is harmless: without a frame in between it sets the same target and ramp again.

    `base` is the sequence number of the frame just before the first entry (None: the session's
    start); a snapshot at `base` or at any buffered frame can be continued."""

    def __init__(self, limit: int = REPLAY_LIMIT) -> None:
        self.entries: deque[tuple[int | None, Message]] = deque()
        self.limit = limit
        self.base: int | None = None

    def add(self, seq: int | None, message: Message) -> None:
        self.entries.append((seq, message))
        if len(self.entries) > self.limit:
            self._drop_through(next(s for s, _ in self.entries if s is not None))

    def acknowledged(self, last_seq: int) -> None:
        """The server stored a snapshot covering frames up to `last_seq`: forget them."""
        if any(s == last_seq for s, _ in self.entries):
            self._drop_through(last_seq)

    def after(self, last_seq: int | None) -> list[tuple[int | None, Message]]:
        """What to send again to a session restored at `last_seq`."""
        if last_seq == self.base:
            return list(self.entries)
        for i, (seq, _) in enumerate(self.entries):
            if seq is not None and seq == last_seq:
                return list(self.entries)[i + 1 :]
        raise ResumeError(
            f"the server resumed at frame {last_seq}, but this client only holds messages after frame "
            f"{self.base}: more than {self.limit} messages went unacknowledged"
        )

    def _drop_through(self, seq: int) -> None:
        while self.entries:
            s, _ = self.entries.popleft()
            if s == seq:
                self.base = seq
                return
