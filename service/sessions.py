"""Streaming sessions: per-session state, style transitions, backpressure and snapshots.

A session owns its model state (batch axis of 1), its style weights as a `{style: weight}` dict
(current and transition target; the vector over the model's styles is built at each step, so
the model's style set may change under a live session) and a bounded queue of pending work.
Frames beyond the queue bound push out the oldest *frame*, and the next reply reports how many
were dropped: the newest frames win and memory stays bounded. Control messages are never
dropped once queued; beyond the bound they are refused at the door (`queue_full`). Snapshots hold everything needed to continue exactly where a session left
off, on this replica or another (`service.session_store` keeps them).
"""

from __future__ import annotations

import base64
import functools
import json
import secrets
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from models.interface import State, StreamingModel
from models.motion import rate
from models.motion.retarget_stream import FrameRetargeter

from . import pipelines
from .protocol import End, ProtocolError, Reset, SetStyle


@dataclass
class FrameItem:
    seq: int
    root: np.ndarray
    rotations: np.ndarray
    received: float  # perf_counter at arrival
    control: np.ndarray | None = None  # (5,) a controller session's tick (protocol `control`), else None


@dataclass
class ControlItem:
    message: SetStyle | Reset | End


class Held(NamedTuple):
    """Rate adaptation (`models.motion.rate`): the latest model outputs, oldest first, and the
    latest input frame (model skeleton)."""

    outputs_root: np.ndarray  # (rate.HISTORY, 3)
    outputs_rotations: np.ndarray  # (rate.HISTORY, J, 4)
    input_root: np.ndarray
    input_rotations: np.ndarray

    @classmethod
    def restore(cls, held: dict[str, np.ndarray]) -> Held | None:
        """From a snapshot's `held`; None for one saved before rates were interpolated (it lacks
        the input pose and the earlier outputs), so the next frame starts the rate afresh."""
        return cls(**held) if set(held) == set(cls._fields) else None


@dataclass
class Snapshot:
    """Everything needed to continue a session exactly where it left off. Held in memory as is
    (model states are never modified in place, so no copy is needed); `to_bytes`/`from_bytes`
    give the portable form for a shared store (`from_bytes` also reads `to_json`'s, the form
    stores held before)."""

    session_id: str
    token: str
    model: str
    skeleton: str
    bvh_header: str | None
    fps: float
    encoding: str
    weights: dict[str, float]
    target: dict[str, float]
    transition_left: int
    last_seq: int | None
    clock: float
    held: dict[str, np.ndarray]  # the held output (rate adaptation); empty before the first frame
    state: State
    saved_at: float
    # the reply to frame `last_seq` (root, rotations in the client's skeleton), for a client whose
    # copy was lost with the connection; empty before the first frame
    last_output: dict[str, np.ndarray] = field(default_factory=dict)
    rig: dict = field(
        default_factory=dict
    )  # the start message's rig options (joints, joint_map, units, up, handedness)
    owner: str = ""  # the tenant that opened it (`limits.Principal.tenant`): only it may resume
    pipeline: str = "full"  # `model`'s pipeline (`service.pipelines`); a snapshot saved before pipelines: full
    # the retargeter's stream state ({"hinges": (1, 4, 4)}, `FrameRetargeter.init_state`); empty in a
    # snapshot saved before it had one, whose session then learns its client's hinges afresh
    retarget: dict[str, np.ndarray] = field(default_factory=dict)

    def to_bytes(self) -> bytes:
        """`SNAPSHOT_MAGIC`, one line of JSON (the other fields, and each array's name, dtype and
        shape), then the arrays' raw bytes: exact. A crowd snapshots every character every
        `snapshot_every` ticks on the event loop; JSON with base64 arrays took ~50 us a character
        (JSON's scan of ~12 kB of text), this ~26 us (the header's JSON and each array's
        bookkeeping; LTI, 25 arrays), and stores ~25 % fewer bytes."""
        header = {k: v for k, v in self.__dict__.items() if k not in ARRAY_FIELDS}
        layout: dict[str, list[list]] = {}
        blobs: list[memoryview] = []
        for group in ARRAY_FIELDS:
            layout[group] = []
            for name, value in getattr(self, group).items():
                array = np.asarray(value)
                array = array if array.flags.c_contiguous else array.copy()  # ascontiguousarray makes 0-d 1-d
                layout[group].append([name, array.dtype.str, list(array.shape)])
                blobs.append(array.data)
        header["arrays"] = layout
        return b"".join([SNAPSHOT_MAGIC, json.dumps(header).encode(), b"\n", *blobs])

    @classmethod
    def from_bytes(cls, data: bytes | str) -> Snapshot:
        """A snapshot from `to_bytes`, or from `to_json` (written by a replica of an earlier
        version: a rolling upgrade resumes its sessions)."""
        if isinstance(data, str) or data[:1] == b"{":
            return cls.from_json(data)
        if not data.startswith(SNAPSHOT_MAGIC):
            raise ValueError("not a stylestream session snapshot")
        end = data.index(b"\n", len(SNAPSHOT_MAGIC))
        fields = json.loads(data[len(SNAPSHOT_MAGIC) : end])
        offset = end + 1
        for group, arrays in fields.pop("arrays").items():
            fields[group] = {}
            for name, dtype, shape in arrays:
                kind = np.dtype(dtype)
                count = int(np.prod(shape, dtype=np.int64))
                fields[group][name] = np.frombuffer(data, kind, count, offset).reshape(shape).copy()
                offset += count * kind.itemsize
        if offset != len(data):
            raise ValueError("session snapshot: its arrays do not fill it")
        return cls(**fields)

    def to_json(self) -> str:
        """The form stores held before `to_bytes` (still read by `from_bytes`)."""
        return json.dumps(
            {
                **self.__dict__,
                "held": encode_state(self.held),
                "state": encode_state(self.state),
                "last_output": encode_state(self.last_output),
                "retarget": encode_state(self.retarget),
            }
        )

    @classmethod
    def from_json(cls, text: str | bytes) -> Snapshot:
        data = json.loads(text)
        for name in ARRAY_FIELDS:
            data[name] = decode_state(data.get(name) or {})
        return cls(**data)


SNAPSHOT_MAGIC = b"stylestream-snapshot/2\n"
ARRAY_FIELDS = ("held", "state", "last_output", "retarget")  # a snapshot's fields that are {name: array}


def encode_state(state: State) -> dict[str, dict]:
    """Arrays as dtype, shape and base64 of their raw bytes: exact, and ~30x faster than
    `np.savez` (a snapshot is encoded every `snapshot_every` frames of every session)."""
    out = {}
    for name, value in state.items():
        array = np.ascontiguousarray(value)
        out[name] = {
            "dtype": array.dtype.str,
            "shape": list(array.shape),
            "data": base64.b64encode(array.tobytes()).decode("ascii"),
        }
    return out


def decode_state(data: dict[str, dict]) -> State:
    return {
        name: np.frombuffer(base64.b64decode(entry["data"]), dtype=np.dtype(entry["dtype"]))
        .reshape(entry["shape"])
        .copy()
        for name, entry in data.items()
    }


@dataclass
class Session:
    model: StreamingModel
    skeleton: str
    fps: float
    encoding: str
    weights: dict[str, float]  # {style: weight}, intensity included
    state: State
    bvh_header: str | None = None
    rig: dict = field(default_factory=dict)  # joints, joint_map, units, up, handedness as started
    owner: str = ""  # the tenant that opened it (`limits.Principal.tenant`)
    caller: str = ""  # who opened it (`limits.Principal.id`): their closed sessions are capped
    id: str = field(default_factory=lambda: uuid.uuid4().hex)
    token: str = field(default_factory=lambda: secrets.token_urlsafe(24))
    target: dict[str, float] = field(default_factory=dict)  # where a style transition goes (at its end: the weights)
    transition_left: int = 0
    last_seq: int | None = None
    dropped_pending: int = 0
    ended: bool = False
    clock: float = -1.0  # the latest frame's lead on the latest model step, in model frames; < 0 before any
    held: Held | None = None  # None until the first model step
    last_output: dict[str, np.ndarray] = field(default_factory=dict)  # the reply to `last_seq`
    # the retargeter's state for this stream (`FrameRetargeter.to_model`; a model-skeleton client
    # leaves it as it is); a reset keeps it: it learns the client's rig, not the motion
    hinges: np.ndarray = field(default_factory=FrameRetargeter.init_state)
    frames_since_snapshot: int = 0
    queue_size: int = 8
    pending: deque[FrameItem | ControlItem] = field(default_factory=deque)

    # ---- styles ----------------------------------------------------------------
    def set_style(self, target: dict[str, float], transition_frames: int) -> None:
        """Move to `target` weights (from `protocol.requested_weights`) over `transition_frames`."""
        self.target = target
        self.transition_left = transition_frames
        if transition_frames == 0:
            self.weights = dict(target)

    def advance_style(self) -> dict[str, float]:
        """Style weights for the next frame: a linear ramp over the remaining transition frames."""
        if self.transition_left > 0:
            cur, tgt = self.weights, self.target
            self.weights = {
                k: cur.get(k, 0.0) + (tgt.get(k, 0.0) - cur.get(k, 0.0)) / self.transition_left for k in {**cur, **tgt}
            }
            self.transition_left -= 1
        return dict(self.weights)

    def styles_gone(self, styles: list[str]) -> list[str]:
        """The styles of the mix (current or target) that are not among `styles`."""
        return [k for k in {**self.weights, **self.target} if k not in styles]

    def drop_deleted(self, styles: list[str]) -> list[str]:
        """Forget styles the model no longer has (deleted uploads): their share of the mix passes
        the input through from now on. Returns those that had weight, to tell the client."""
        gone = self.styles_gone(styles)
        if not gone:
            return []
        had = sorted(k for k in gone if self.weights.get(k, 0.0) > 0 or self.target.get(k, 0.0) > 0)
        self.weights = {k: v for k, v in self.weights.items() if k not in gone}
        self.target = {k: v for k, v in self.target.items() if k not in gone}
        return had

    def reset(self) -> None:
        """Recurrent state back to its start. `last_seq` stays: it marks how far the client's
        stream has been consumed, which resume needs whatever the state holds."""
        self.state = self.model.init_state(1)
        self.clock, self.held = -1.0, None

    # ---- frame rate ----------------------------------------------------------------
    @functools.cached_property
    def lag(self) -> float:
        """The output's delay behind the input, in model frames (`models.motion.rate`)."""
        return rate.output_lag(self.model.fps, self.fps)

    def model_inputs(self, root: np.ndarray, rotations: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """The model steps due for this input frame (model skeleton), each with its input pose, so
        the model runs at its own frame rate on the input at its own times: at 120 fps in, every
        4th frame steps; at 24 fps, some frames step twice. No look-ahead: each pose is
        interpolated between the previous input frame and this one."""
        root, rotations = np.asarray(root, np.float64), np.asarray(rotations, np.float64)  # as a crowd's rows
        if self.held is None:
            self.clock = -1.0  # no output yet (a first step failed): start the rate afresh
        clock, steps, weights = rate.steps_due(np.array([self.clock]), self.model.fps / self.fps)
        self.clock = float(clock[0])
        if self.held is None:
            return [(root, rotations)] * int(steps[0])
        r0, q0 = self.held.input_root[None], self.held.input_rotations[None]
        inputs = []
        for k in range(int(steps[0])):
            r, q = rate.blend(r0, q0, root[None], rotations[None], weights[0, k : k + 1])
            inputs.append((r[0], q[0]))
        self.held = self.held._replace(input_root=root, input_rotations=rotations)
        return inputs

    def hold(
        self, root: np.ndarray, rotations: np.ndarray, input_root: np.ndarray, input_rotations: np.ndarray
    ) -> None:
        """Keep a model output made for the input frame (`input_root`, `input_rotations`); the
        first one stands for the earlier ones too."""
        root, rotations = np.asarray(root, np.float64), np.asarray(rotations, np.float64)  # as a crowd's rows
        if self.held is None:
            roots = np.repeat(root[None], rate.HISTORY, axis=0)
            rots = np.repeat(rotations[None], rate.HISTORY, axis=0)
        else:
            roots = rate.push(self.held.outputs_root[None], root[None])[0]
            rots = rate.push(self.held.outputs_rotations[None], rotations[None])[0]
        self.held = Held(roots, rots, np.asarray(input_root, np.float64), np.asarray(input_rotations, np.float64))

    def held_output(self) -> tuple[np.ndarray, np.ndarray]:
        """The output for the latest input frame: the model's output `lag` model frames before
        it, root and pose at that one instant on the parabola through the three latest model
        outputs (the first frame always steps, so there is one)."""
        h = self.held
        if h is None:
            raise RuntimeError("no model output held yet")
        u = rate.output_weight(np.array([self.clock]), self.lag)
        out_root, out_rot = rate.interpolate(h.outputs_root[None], h.outputs_rotations[None], u)
        return out_root[0], out_rot[0]

    # ---- backpressure -----------------------------------------------------------
    def enqueue(self, item: FrameItem | ControlItem) -> None:
        """Queue work. A frame beyond `queue_size` pushes out the oldest frame; a control message
        beyond `queue_size` controls is refused (`queue_full`): never dropped once queued, so
        they are bounded at the door instead."""
        if isinstance(item, ControlItem):
            if sum(isinstance(i, ControlItem) for i in self.pending) >= self.queue_size:
                raise ProtocolError(
                    "queue_full",
                    f"{self.queue_size} control messages are already waiting; this one was not taken, send it again later",
                )
        else:
            frames = sum(isinstance(i, FrameItem) for i in self.pending)
            if frames >= self.queue_size:
                oldest = next(i for i in self.pending if isinstance(i, FrameItem))
                self.pending.remove(oldest)
                self.dropped_pending += 1
        self.pending.append(item)

    def take_dropped(self) -> int:
        n, self.dropped_pending = self.dropped_pending, 0
        return n

    # ---- snapshots --------------------------------------------------------------
    def snapshot_due(self, every: int) -> bool:
        """Count a stylised frame; true every `every` frames (counted, not read off the client's
        sequence numbers, which need not be consecutive)."""
        self.frames_since_snapshot += 1
        if self.frames_since_snapshot < every:
            return False
        self.frames_since_snapshot = 0
        return True

    def snapshot(self) -> Snapshot:
        model, pipeline = pipelines.split(self.model.name)
        return Snapshot(
            session_id=self.id,
            token=self.token,
            model=model,
            pipeline=pipeline,
            skeleton=self.skeleton,
            bvh_header=self.bvh_header,
            fps=self.fps,
            encoding=self.encoding,
            weights=dict(self.weights),
            target=dict(self.target),
            transition_left=self.transition_left,
            last_seq=self.last_seq,
            clock=self.clock,
            held={} if self.held is None else self.held._asdict(),
            state=self.state,
            saved_at=time.time(),
            last_output=dict(self.last_output),
            rig=dict(self.rig),
            owner=self.owner,
            retarget={"hinges": self.hinges.copy()},
        )

    @classmethod
    def restore(cls, snap: Snapshot, model: StreamingModel, queue_size: int, caller: str = "") -> Session:
        return cls(
            model=model,
            skeleton=snap.skeleton,
            fps=snap.fps,
            encoding=snap.encoding,
            weights=dict(snap.weights),
            state=dict(snap.state),
            bvh_header=snap.bvh_header,
            id=snap.session_id,
            token=snap.token,
            target=dict(snap.target),
            transition_left=snap.transition_left,
            last_seq=snap.last_seq,
            queue_size=queue_size,
            clock=snap.clock,
            held=Held.restore(snap.held),
            last_output=dict(snap.last_output),
            rig=dict(snap.rig),
            owner=snap.owner,
            caller=caller,
            hinges=restored_hinges(snap),
        )


def restored_hinges(snap: Snapshot) -> np.ndarray:
    """A snapshot's retarget state (1, 4, 4), fresh for one saved before there was one."""
    hinges = snap.retarget.get("hinges")
    return FrameRetargeter.init_state() if hinges is None else np.array(hinges, np.float64).reshape(1, 4, 4)
