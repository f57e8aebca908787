"""Wire protocol v1 of `WS /v1/stream` (documented with examples in docs/protocol.md).

Text messages are JSON objects with a "type". Frames may instead travel as binary messages:
a fixed little-endian layout, header then float32 payload:

    offset 0  uint32  seq            client's sequence number (echoed back)
    offset 4  uint16  kind           1 = frame
    offset 6  uint16  dropped        server -> client: frames dropped since the last reply; 0 from clients
    offset 8  float32 root[3]        root (Hips) translation
    offset 20 float32 rot[J][4]      local joint rotations, quaternions x, y, z, w, in the session's joint order
"""

from __future__ import annotations

import struct
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, field_validator

from models.interface import style_weights
from models.motion.humanoid import PRESET_NAMES, ROLES

from . import frame_check as FC
from .frame_check import check_frame

PROTOCOL_VERSION = 1
BINARY_HEADER = struct.Struct("<IHH")
KIND_FRAME = 1


class ProtocolError(Exception):
    """A client error, reported as a typed error message. `fatal` ones close the session."""

    def __init__(
        self,
        code: str,
        message: str,
        seq: int | None = None,
        fatal: bool = False,
        close_code: int = 1008,
        character: int | None = None,  # in a crowd: the character it concerns
    ):
        super().__init__(message)
        self.code, self.message, self.seq, self.fatal, self.close_code = code, message, seq, fatal, close_code
        self.character = character


class _Message(BaseModel):
    # strict: "5" is not a number nor true a weight, so a client's type slip is an error, not a guess
    model_config = ConfigDict(extra="forbid", strict=True)


MAX_CONTROL_SPEED = 12.0  # m/s: faster than any sprint, so a wild stick value is an error, not a teleport
StyleMix = dict[str, Annotated[float, Field(ge=0, allow_inf_nan=False)]]  # an infinite weight made every weight NaN


class CharacterSpec(_Message):
    """What one character is: its model, style and rig (a session's `start`, or one member of a
    crowd's `characters`)."""

    model: str
    # "core": the method's published core alone, without the fitted stages after it (`service.pipelines`)
    pipeline: Literal["full", "core"] = "full"
    style: str | None = None
    mix: StyleMix | None = None  # {style: weight}; alternative to `style`
    intensity: float = Field(default=1.0, ge=0.0, le=2.0)
    # a preset rig (models.motion.humanoid_presets); Literal of a tuple: pydantic reads it, mypy cannot
    skeleton: Literal[PRESET_NAMES] | None = "bandai-namco"  # type: ignore[valid-type]
    joints: list[Annotated[str, Field(max_length=200)]] | None = Field(
        default=None,
        max_length=1024,
        description="with `skeleton`: the preset's joints the frames carry, in their order",
    )
    bvh_header: str | None = Field(
        default=None, max_length=200_000, description="BVH HIERARCHY text, instead of `skeleton`"
    )
    joint_map: dict[str, Literal[ROLES] | None] | None = Field(  # type: ignore[valid-type]
        default=None,
        max_length=1024,
        description="{client joint: body role or null}: completes or overrides the name matching",
    )
    units: Literal["m", "dm", "cm", "mm", "in"] | None = None  # default: read from the leg length
    up: Literal["y", "z"] | None = None  # default: read from a standing rest pose, else y
    handedness: Literal["right", "left"] = "right"

    def rig_options(self) -> dict:
        """The rig choices beyond `skeleton` and `bvh_header` (kept with the session for resumes)."""
        return {
            k: v
            for k, v in (
                ("joints", self.joints),
                ("joint_map", self.joint_map),
                ("units", self.units),
                ("up", self.up),
                ("handedness", self.handedness),
            )
            if v is not None and (k != "handedness" or v != "right")
        }


def _supported_version(v: int) -> int:
    if v != PROTOCOL_VERSION:
        raise ValueError(f"protocol version {v} not supported (server speaks {PROTOCOL_VERSION})")
    return v


class Start(CharacterSpec):
    type: Literal["start"]
    version: int = PROTOCOL_VERSION
    fps: float = Field(default=30.0, gt=0, le=240)
    # "binary-faded": binary replies that end in one more float32, the frame's `faded`
    encoding: Literal["json", "binary", "binary-faded"] = "json"
    resume_token: str | None = None
    snapshot_acks: bool = False  # send {"type": "snapshot", "last_seq": n} once a snapshot is stored

    _supported = field_validator("version")(_supported_version)


MAX_CHARACTER_ID = 2**32 - 1
CharacterIds = Annotated[list[Annotated[int, Field(ge=0, le=MAX_CHARACTER_ID)]], Field(min_length=1, max_length=65_535)]


class CrowdCharacter(CharacterSpec):
    id: int = Field(ge=0, le=MAX_CHARACTER_ID, description="the client's name for the character in ticks and replies")
    resume_token: str | None = Field(
        default=None,
        max_length=200,
        description="continue the character (or session) this token was given for, exactly where it left "
        "off: its model, style and rig are the stored ones",
    )


CharacterList = Annotated[list[CrowdCharacter], Field(min_length=1, max_length=65_535)]


class CrowdStart(_Message):
    """Opens a crowd connection (protocol v1.1): many characters, one binary tick per frame time."""

    type: Literal["crowd"]
    version: int = PROTOCOL_VERSION
    fps: float = Field(default=30.0, gt=0, le=240)
    characters: CharacterList
    faded: bool = Field(default=False, description="tick replies end in each listed character's `faded` (float32)")

    _supported = field_validator("version")(_supported_version)


class Join(_Message):
    type: Literal["join"]
    characters: CharacterList


class Leave(_Message):
    type: Literal["leave"]
    characters: CharacterIds


class Frame(_Message):
    type: Literal["frame"]
    seq: int = Field(ge=0, lt=2**32)
    root: list[float] = Field(min_length=3, max_length=3)
    rotations: list[list[float]]


class SetStyle(_Message):
    type: Literal["style"]
    characters: CharacterIds | None = None  # in a crowd: which characters (default: every one)
    style: str | None = None
    mix: StyleMix | None = None
    intensity: float = Field(default=1.0, ge=0.0, le=2.0)
    transition_frames: int = Field(default=0, ge=0, le=10_000)


class Control(_Message):
    """One tick of a controller session (LPN-FiLM): the desired motion instead of a mocap frame;
    the reply is the synthesised frame, like a frame's reply. Conventions as in the character
    frame of `models.motion.features`: velocity = [forward, side] in m/s, side > 0 to the
    character's left, both in the frame of the desired facing; facing = yaw in radians about +Y,
    0 = facing world +Z."""

    type: Literal["control"]
    seq: int = Field(ge=0, lt=2**32)
    velocity: list[Annotated[float, Field(ge=-MAX_CONTROL_SPEED, le=MAX_CONTROL_SPEED, allow_inf_nan=False)]] = Field(
        min_length=2, max_length=2
    )
    facing: float = Field(ge=-1e4, le=1e4, allow_inf_nan=False)
    gait: Literal["walk", "run"] = "walk"


class Reset(_Message):
    type: Literal["reset"]
    characters: CharacterIds | None = None  # in a crowd: which characters (default: every one)


class End(_Message):
    type: Literal["end"]


ClientMessage = Annotated[
    Start | CrowdStart | Frame | Control | SetStyle | Reset | End | Join | Leave, Field(discriminator="type")
]
client_message = TypeAdapter(ClientMessage)


def mix_of(style: str | None, mix: StyleMix | None) -> StyleMix:
    if style is not None and mix is None:
        return {style: 1.0}
    if mix is not None and style is None:
        return dict(mix)
    raise ProtocolError("bad_style", "give exactly one of 'style' or 'mix'")


def requested_weights(model, style: str | None, mix: StyleMix | None, intensity: float) -> dict[str, float]:
    """The style a start or style message asks for, as weights over the model's styles; the one
    place that turns a bad request into a typed error."""
    try:
        return style_weights(model, mix_of(style, mix), intensity)
    except KeyError as exc:
        raise ProtocolError("unknown_style", str(exc).strip('"')) from None
    except ValueError as exc:
        raise ProtocolError("bad_style", str(exc)) from None


def parse_text(text: str) -> Start | CrowdStart | Frame | Control | SetStyle | Reset | End | Join | Leave:
    from pydantic import ValidationError

    try:
        return client_message.validate_json(text)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ()))
        code = "bad_json" if first["type"].startswith("json") else "bad_message"
        raise ProtocolError(code, f"{where}: {first['msg']}" if where else first["msg"]) from None


def control_array(message: Control) -> np.ndarray:
    """The (5,) row of `models.interface.FrameBatch.control`: forward, side (m/s), facing, gait, flag."""
    forward, side = message.velocity
    return np.array([forward, side, message.facing, 1.0 if message.gait == "run" else 0.0, 1.0])


def frame_arrays(frame: Frame, num_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate a JSON frame's shape and values; returns (root (3,), rotations (J, 4))."""
    if len(frame.rotations) != num_joints or any(len(q) != 4 for q in frame.rotations):
        raise ProtocolError("bad_frame", f"rotations must be {num_joints} quaternions [x, y, z, w]", frame.seq)
    root = np.asarray(frame.root, dtype=np.float64)
    rot = np.asarray(frame.rotations, dtype=np.float64)
    return check_values(root, rot, frame.seq)


def check_values(root: np.ndarray, rot: np.ndarray, seq: int) -> tuple[np.ndarray, np.ndarray]:
    """Finite values, non-zero quaternions (returned normalised, as float64), a root within 1e6
    units. One compiled pass (`frame_check`): this runs on every frame."""
    root_out, rot_out = np.empty(3), np.empty((len(rot), 4))
    status = check_frame(root, rot, root_out, rot_out)
    if status != FC.OK:
        raise ProtocolError("bad_frame", FRAME_CHECK_ERRORS[status], seq)
    return root_out, rot_out


FRAME_CHECK_ERRORS = {
    FC.NOT_FINITE: "frame contains NaN or Inf",
    FC.ZERO_QUATERNION: "zero-length quaternion",
    FC.QUATERNION_RANGE: "quaternion components out of range",
    FC.ROOT_RANGE: "root translation out of range",
}


def binary_frame_size(num_joints: int) -> int:
    return BINARY_HEADER.size + 4 * (3 + 4 * num_joints)


def decode_binary(data: bytes, num_joints: int) -> tuple[int, np.ndarray, np.ndarray]:
    expected = binary_frame_size(num_joints)
    if len(data) < BINARY_HEADER.size:
        raise ProtocolError("bad_frame", f"binary message of {len(data)} bytes is shorter than the 8-byte header")
    seq, kind, _ = BINARY_HEADER.unpack_from(data)
    if kind != KIND_FRAME:
        raise ProtocolError("bad_frame", f"unknown binary message kind {kind}", seq)
    if len(data) != expected:
        raise ProtocolError(
            "bad_frame", f"binary frame must be {expected} bytes for {num_joints} joints, got {len(data)}", seq
        )
    payload = np.frombuffer(data, dtype="<f4", offset=BINARY_HEADER.size)  # a view; the check copies to float64
    root, rot = check_values(payload[:3], payload[3:].reshape(num_joints, 4), seq)
    return seq, root, rot


def encode_binary(seq: int, root: np.ndarray, rot: np.ndarray, dropped: int = 0, faded: float | None = None) -> bytes:
    """A binary frame reply; `faded` (encoding "binary-faded") is one more float32 at its end."""
    header = BINARY_HEADER.pack(seq, KIND_FRAME, min(dropped, 0xFFFF))
    tail = () if faded is None else (np.array([faded]),)
    return header + np.concatenate([root.ravel(), rot.ravel(), *tail]).astype("<f4").tobytes()


def frame_message(seq: int, root: np.ndarray, rot: np.ndarray, dropped: int = 0, faded: float | None = None) -> dict:
    """A JSON frame reply; `faded` (0..1: how far the frame was faded toward the input as content
    the model was not trained on, `models.motion.novelty`) where the pipeline has that stage."""
    message = {"type": "frame", "seq": seq, "root": root.tolist(), "rotations": rot.tolist(), "dropped": dropped}
    if faded is not None:
        message["faded"] = round(float(faded), 3)
    return message


def close_reason(text: str) -> str:
    """`text` cut to the 123 UTF-8 bytes a WebSocket close reason may hold. Error messages quote
    client input (field names), so they may hold any character: cutting by characters, or a lone
    surrogate that UTF-8 cannot encode, made the close itself fail and the connection drop."""
    return text.encode("utf-8", "replace")[:123].decode("utf-8", "ignore")


def error_message(code: str, message: str, seq: int | None = None, character: int | None = None) -> dict:
    if character is None:
        return {"type": "error", "code": code, "message": message, "seq": seq}
    return {"type": "error", "code": code, "message": message, "seq": seq, "character": character}


# ---- crowd ticks (protocol v1.1) ----------------------------------------------------------
TICK_HEADER = struct.Struct("<IHHI")  # seq, kind, characters, dropped (server -> client; 0 from clients)
KIND_TICK = 2
KIND_CONTROL_TICK = 3  # each character's desired motion: forward, side (m/s), facing (rad), gait (0 walk, 1 run)
CONTROL_FLOATS = 4


def decode_tick(data: bytes) -> tuple[int, int, bytes, np.ndarray]:
    """A crowd's binary tick: (seq, kind, the character ids as sent (uint32 LE), float32 payload
    view). Which floats belong to whom is the crowd's to say (`service.crowd.Plan`)."""
    if len(data) < TICK_HEADER.size:
        raise ProtocolError("bad_frame", f"binary message of {len(data)} bytes is shorter than the 12-byte tick header")
    seq, kind, count, _ = TICK_HEADER.unpack_from(data)
    if kind not in (KIND_TICK, KIND_CONTROL_TICK):
        raise ProtocolError(
            "bad_frame",
            f"a crowd sends ticks (binary kind {KIND_TICK}) or controller ticks (kind {KIND_CONTROL_TICK}), got kind {kind}",
            seq,
        )
    start = TICK_HEADER.size + 4 * count
    if len(data) < start or (len(data) - start) % 4:
        raise ProtocolError("bad_frame", f"a tick of {count} characters cannot be {len(data)} bytes", seq)
    return seq, kind, data[TICK_HEADER.size : start], np.frombuffer(data, "<f4", offset=start)


def control_rows(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 4) controller-tick values -> the (n, 5) rows of `FrameBatch.control` (as
    `control_array` makes them) and which rows are valid (finite, speeds within
    `MAX_CONTROL_SPEED`, facing within 1e4 rad, gait 0 or 1), as a `control` message's fields are."""
    v = values.astype(np.float64)
    ok = (
        np.isfinite(v).all(1)
        & (np.abs(v[:, :2]) <= MAX_CONTROL_SPEED).all(1)
        & (np.abs(v[:, 2]) <= 1e4)
        & np.isin(v[:, 3], (0.0, 1.0))
    )
    return np.concatenate([v, np.ones((len(v), 1))], 1), ok


def encode_tick(
    seq: int, ids: np.ndarray, payload: np.ndarray, dropped: int = 0, faded: np.ndarray | None = None
) -> bytes:
    """A tick (reply); `faded` (a crowd opened with `faded`): one float32 per id after the frames."""
    header = TICK_HEADER.pack(seq, KIND_TICK, len(ids), min(dropped, 0xFFFFFFFF))
    tail = b"" if faded is None else np.asarray(faded).astype("<f4").tobytes()
    return header + ids.astype("<u4").tobytes() + payload.astype("<f4", copy=False).tobytes() + tail
