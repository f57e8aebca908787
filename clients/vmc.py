"""VMC bridge: Virtual Motion Capture (OSC over UDP) in, the avatar restyled, VMC out.

    stylestream vmc --listen 39539 --send-host 127.0.0.1 --send-port 39540 --model lti --style elderly \\
        [--bones upper] [--bone-timeout 1.0]

A VMC sender (VSeeFace, VirtualMotionCapture, Warudo, a tracker app) sends per frame the avatar
root (`/VMC/Ext/Root/Pos`) and each Unity humanoid bone (`/VMC/Ext/Bone/Pos name px py pz qx qy
qz qw`: local position and rotation, Unity axes: left-handed, Y up, metres), plus blend shapes,
eyes, fingers, trackers, `/VMC/Ext/OK`, `/VMC/Ext/T`. The bridge

* **keeps the avatar's proportions**: the body bones the sender sends (Hips, Spine, Chest,
  UpperChest, Neck, Head, shoulders, arms, hands, legs, feet, toes) with their local positions
  *are* the rig: the bridge writes them as a BVH header (`AvatarRig`) and opens a session on it
  (`bvh_header`), so the one humanoid mapping (`models.motion.humanoid`, `retarget_stream` on the
  server) retargets the avatar onto the model skeleton and the stylised frame back onto the
  avatar's own bones; the bridge maps no bone itself. Unity's left-handed frame is brought to a
  right-handed one by mirroring X (positions `x -> -x`, quaternions `(x, y, z, w) -> (x, -y, -z,
  w)`; its own inverse), a sign flip on two arrays. The avatar root is composed into the Hips (the
  rig's translated joint) on the way in and taken out on the way back. The rig changes (a new
  session) only when the body bones or their offsets do (another avatar).
* **converts a frame in a few array operations** (`model_input`, `unity_output`), and decodes
  and encodes OSC on raw bytes (`vmc_osc`): ~0.2 ms a frame of ~55 bones in the bridge (hot; `python -m clients.vmc bench`).
* **passes everything else through**: messages that are not pose messages (blend shapes, eye
  and camera messages, trackers, `/VMC/Ext/OK`, `/VMC/Ext/T`, anything unknown) go out byte for
  byte in the frame's bundle (a bundle without pose messages, or a loose message, at once); bones
  outside the body (fingers, eyes, jaw) and bones outside the **bone mask** (`--bones`: Unity
  names and groups `body`, `upper`, `lower`, `spine`, `head`, `arms`, `legs`; `-Name` removes)
  keep the sender's values.
* **resets a sender's missing bones**: a bone not sent for `--bone-timeout` seconds goes back to
  its rest (identity rotation, its first position), as if the sender had let go of it; until then
  it holds its last value, as VMC receivers do.
* **never freezes**: the session lives on a worker thread (`StyleLink`); a frame the server has
  not answered within `--wait-ms` goes out unstyled, and while the session is down (server
  restarted, token unknown, network gone) frames pass through unstyled and a fresh session is
  opened with backoff, then styling resumes.

Framing: a frame completes when a bundle holding pose messages ends, or, for senders that send
loose messages, on `/VMC/Ext/T`. Output: one bundle per frame (root, every bone the sender has
sent, the passed-through messages in their order; `/VMC/Ext/OK 1` and `/VMC/Ext/T` added when
the sender sent none).

Assumption: bone positions are local to the Unity humanoid parent (the nearest sent ancestor),
and the avatar's bones at identity rotation stand upright (a normalised humanoid, as VRM and VMC
senders send it); the mapping itself does not need a T-pose, only the reading of the rig's up
axis from that rest does.
"""

from __future__ import annotations

import argparse
import json
import logging
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Protocol

import numpy as np

from . import vmc_osc as osc

log = logging.getLogger(__name__)

ROOT_ADDRESS = "/VMC/Ext/Root/Pos"
BONE_ADDRESS = "/VMC/Ext/Bone/Pos"
OK_ADDRESS = "/VMC/Ext/OK"
TIME_ADDRESS = "/VMC/Ext/T"
_BONE_HEAD = osc.pose_head(BONE_ADDRESS)  # a bone message in the usual shape starts with these bytes
_BONE_AT, _ROOT_AT = osc.osc_string(BONE_ADDRESS), osc.osc_string(ROOT_ADDRESS)  # any pose message does with these
_OK_AT, _TIME_AT = osc.osc_string(OK_ADDRESS), osc.osc_string(TIME_ADDRESS)

# Unity body bones (HumanBodyBones) and their humanoid parents, depth first.
BODY_PARENTS: dict[str, str | None] = {
    "Hips": None,
    "Spine": "Hips",
    "Chest": "Spine",
    "UpperChest": "Chest",
    "Neck": "UpperChest",
    "Head": "Neck",
    **{
        f"{s}{b}": p if p == "UpperChest" else f"{s}{p}"
        for s in ("Left", "Right")
        for b, p in (
            ("Shoulder", "UpperChest"),
            ("UpperArm", "Shoulder"),
            ("LowerArm", "UpperArm"),
            ("Hand", "LowerArm"),
        )
    },
    **{
        f"{s}{b}": p if p == "Hips" else f"{s}{p}"
        for s in ("Left", "Right")
        for b, p in (("UpperLeg", "Hips"), ("LowerLeg", "UpperLeg"), ("Foot", "LowerLeg"), ("Toes", "Foot"))
    },
}
BODY_BONES = tuple(BODY_PARENTS)
_SIDES = ("Left", "Right")
BONE_GROUPS: dict[str, tuple[str, ...]] = {
    "body": BODY_BONES,
    "spine": ("Spine", "Chest", "UpperChest"),
    "head": ("Neck", "Head"),
    "arms": tuple(f"{s}{b}" for s in _SIDES for b in ("Shoulder", "UpperArm", "LowerArm", "Hand")),
    "legs": tuple(f"{s}{b}" for s in _SIDES for b in ("UpperLeg", "LowerLeg", "Foot", "Toes")),
}
BONE_GROUPS["upper"] = BONE_GROUPS["spine"] + BONE_GROUPS["head"] + BONE_GROUPS["arms"]
BONE_GROUPS["lower"] = ("Hips",) + BONE_GROUPS["legs"]

MIRROR_P = np.array([-1.0, 1.0, 1.0])  # Unity (left-handed) <-> right-handed: x -> -x
MIRROR_Q = np.array([1.0, -1.0, -1.0, 1.0])  # the same reflection on quaternions (x, y, z, w)
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def parse_bones(spec: str) -> frozenset[str]:
    """The bone mask of `--bones`: comma-separated Unity body bone names and groups
    (`BONE_GROUPS`), a leading `-` removing; e.g. `upper`, `body,-Head`, `arms,Spine`."""
    keep: set[str] = set()
    unknown = []
    for raw in (p.strip() for p in spec.split(",")):
        if not raw:
            continue
        drop, name = raw.startswith("-"), raw.lstrip("-")
        bones = (name,) if name in BODY_PARENTS else BONE_GROUPS.get(name.lower())  # "Head" the bone, "head" the group
        if bones is None:
            unknown.append(raw)
        elif drop:
            keep.difference_update(bones)
        else:
            keep.update(bones)
    if unknown:
        raise ValueError(
            f"--bones: unknown {', '.join(unknown)} (groups: {', '.join(BONE_GROUPS)}; bones: {', '.join(BODY_BONES)})"
        )
    return frozenset(keep)


# --------------------------------------------------------------------------- quaternions (x, y, z, w)


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a0, a1, a2, b0, b1, b2 = a[..., 0], a[..., 1], a[..., 2], b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)  # np.cross costs ~10x


def _qapply(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def _qinv(q: np.ndarray) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def _unit(q: np.ndarray) -> np.ndarray:
    """Unit quaternions; a zero one (a broken sender) becomes the identity."""
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(n > 1e-9, q / np.maximum(n, 1e-9), IDENTITY)


# --------------------------------------------------------------------------- what the sender has sent


class VmcState:
    """What a VMC receiver holds: the avatar root and, per bone name, its last local position and
    rotation (Unity axes, as sent), when it was last sent and its rest position (the first one
    sent). Bones are slots in growing arrays, so a frame updates and reads them in one go."""

    def __init__(self, bone_timeout_s: float = 1.0) -> None:
        self.bone_timeout_s = bone_timeout_s
        self.names: list[str] = []
        self.slot: dict[str, int] = {}
        self._key_slot: dict[bytes, int] = {}  # the same by the name's bytes on the wire
        self.pos = np.zeros((0, 3))
        self.rot = np.zeros((0, 4))
        self.rest = np.zeros((0, 3))
        self.seen = np.zeros(0)
        self.root_pos, self.root_rot = np.zeros(3), IDENTITY.copy()
        self.root_message: bytes | None = None  # re-sent as it came
        self.version = 0  # bumped when a bone name appears

    def _slots(self, names: list[bytes]) -> list[int]:
        """The slot of each name (bytes as on the wire); a new name gets a new slot."""
        get = self._key_slot.get
        return [s if s is not None else self._add(n) for n, s in zip(names, [get(n) for n in names])]

    def _add(self, key: bytes) -> int:
        name = key.decode("utf-8", "replace")
        s = self._key_slot[key] = self.slot.setdefault(name, len(self.names))
        if s == len(self.names):
            self.names.append(name)
            self.version += 1
            self.pos, self.rot = np.vstack([self.pos, np.zeros(3)]), np.vstack([self.rot, IDENTITY])
            self.rest, self.seen = np.vstack([self.rest, np.full(3, np.nan)]), np.append(self.seen, -np.inf)
        return s

    def update(self, names: list[str] | list[bytes], values: np.ndarray, now: float) -> None:
        """Bones `names` took `values` (N, 7: px, py, pz, qx, qy, qz, qw) at time `now`."""
        if not len(names):
            return
        idx = np.array(self._slots([n.encode() if isinstance(n, str) else n for n in names]))
        v = np.asarray(values, dtype=np.float64).reshape(len(idx), 7)
        self.pos[idx], self.rot[idx], self.seen[idx] = v[:, :3], v[:, 3:7], now
        fresh = idx[np.isnan(self.rest[idx, 0])]
        self.rest[fresh] = self.pos[fresh]

    def expire(self, now: float) -> np.ndarray:
        """Reset bones not sent for `bone_timeout_s` to their rest; returns the reset slots."""
        stale = np.flatnonzero(now - self.seen > self.bone_timeout_s)
        if len(stale):
            self.rot[stale], self.pos[stale] = IDENTITY, self.rest[stale]
            self.seen[stale] = np.inf  # reset once; a new value brings the bone back
        return stale

    def body(self) -> dict[str, np.ndarray]:
        """{body bone: local position} of the body bones sent so far."""
        return {b: self.pos[self.slot[b]] for b in BODY_BONES if b in self.slot}


@dataclass
class Received:
    """What one datagram gave: `forward`, datagrams to send on as they are; `frames`, per
    completed frame the raw messages to pass through in it (the state is already updated)."""

    forward: list[bytes] = field(default_factory=list)
    frames: list[list[bytes]] = field(default_factory=list)


class VmcReceiver:
    """Frames out of datagrams: pose messages update `state`; a bundle holding pose messages
    completes a frame; loose messages complete one on `/VMC/Ext/T` (or when a bone comes again,
    for senders that send no T); every other message is passed through."""

    def __init__(self, state: VmcState) -> None:
        self.state = state
        self._pending: list[bytes] = []  # loose non-pose messages of the loose frame in progress
        self._loose: set[bytes] = set()  # bones of the loose frame in progress
        self.bad = 0  # datagrams that were not OSC

    def feed(self, data: bytes, now: float) -> Received:
        out = Received()
        try:
            names: list[bytes] = []
            raw: list[bytes] = []
            passed: list[bytes] = []
            root: tuple | None = None
            for m in osc.elements(data):
                if m.startswith(_BONE_HEAD):  # the usual bone message: split, decoded below all at once
                    name, floats = osc.split_pose(m, 32)
                    names.append(name)
                    raw.append(floats)
                elif m.startswith(_BONE_AT) or m.startswith(_ROOT_AT):
                    pose = osc.decode_pose(m)  # the root, or other argument types
                    if pose is None:
                        passed.append(m)
                    elif m.startswith(_BONE_AT):
                        names.append(pose[0].encode())
                        raw.append(osc.pack_pose(pose[1]))
                    else:
                        root = (pose[1], m)
                else:
                    passed.append(m)
        except osc.OscError as exc:
            self.bad += 1
            log.debug("dropped a datagram that is not OSC: %s", exc)
            return out
        values = np.frombuffer(b"".join(raw), ">f4").reshape(-1, 7)
        is_pose = bool(names) or root is not None
        if data.startswith(osc.BUNDLE_TAG):
            self._apply(names, values, root, now)
            if is_pose:
                out.frames.append(passed)
            elif passed:
                out.forward.append(data)
            return out
        if is_pose:  # a loose pose message: a bone sent again starts the next frame
            keys = names + ([b"<root>"] if root is not None else [])
            if any(k in self._loose for k in keys):
                out.frames.append(self._pending)
                self._pending, self._loose = [], set()
            self._loose.update(keys)
            self._apply(names, values, root, now)
        elif self._loose and passed[0].startswith(_TIME_AT):
            out.frames.append(self._pending + passed)
            self._pending, self._loose = [], set()
        elif self._loose:
            self._pending += passed
        else:
            out.forward.append(data)
        return out

    def _apply(self, names: list[bytes], values: np.ndarray, root: tuple | None, now: float) -> None:
        if root is not None:
            v, message = root
            self.state.root_pos, self.state.root_rot = np.array(v[:3]), _unit(np.array(v[3:7]))
            self.state.root_message = message
        self.state.update(names, values, now)


# --------------------------------------------------------------------------- the avatar's rig


@dataclass(frozen=True)
class AvatarRig:
    """The sender's avatar as the server gets it: its body bones in the header's (depth-first)
    order, their local positions (Unity axes, metres, as sent), the BVH header (right-handed,
    mirrored) that carries them, and the mapping `models.motion.humanoid` reads from it."""

    bones: tuple[str, ...]
    offsets: np.ndarray
    header: str
    report: dict


def _depth_first(present: Iterable[str]) -> list[str]:
    present = set(present)

    def parent(b: str) -> str | None:
        p = BODY_PARENTS[b]
        while p is not None and p not in present:
            p = BODY_PARENTS[p]
        return p

    children: dict[str | None, list[str]] = {}
    for b in BODY_BONES:
        if b in present:
            children.setdefault(parent(b), []).append(b)
    order: list[str] = []
    stack = list(reversed(children.get(None, [])))
    while stack:
        b = stack.pop()
        order.append(b)
        stack.extend(reversed(children.get(b, [])))
    return order


def avatar_rig(body: dict[str, np.ndarray]) -> AvatarRig:
    """The rig of the body bones sent ({Unity bone: local position}); raises
    `models.motion.humanoid.RigError` (naming every missing role) when they are not a humanoid
    the mapping can use, or when their rest does not stand up along Y."""
    from models.motion import bvh as bvhio
    from models.motion.humanoid import RigError, rig_from_bvh
    from models.motion.skeleton import Motion, Skeleton, to_bvh

    if "Hips" not in body:
        raise RigError("missing_roles", "the sender has sent no Hips", ("hips",))
    order = _depth_first(body)  # Hips first: every other body bone hangs below it
    index = {b: k for k, b in enumerate(order)}
    parents = []
    for b in order:
        p = BODY_PARENTS[b]
        while p is not None and p not in index:
            p = BODY_PARENTS[p]
        parents.append(-1 if p is None else index[p])
    offsets = np.array([body[b] for b in order], dtype=np.float64)
    sk = Skeleton(tuple(order), np.array(parents), offsets * MIRROR_P, np.full((len(order), 3), np.nan))
    one = Motion(sk, np.tile(IDENTITY, (1, len(order), 1)), (offsets * MIRROR_P)[None], 60.0)
    header = bvhio.dumps(to_bvh(one), precision=9).split("MOTION")[0]
    rig = rig_from_bvh(header, "VMC avatar")
    if rig.up != "y":
        raise RigError(
            "bad_rig",
            "the avatar's bones at identity rotation do not stand up along Y (the bridge "
            "expects a normalised humanoid, as VMC senders send)",
        )
    return AvatarRig(tuple(order), offsets, header, rig.report())


# --------------------------------------------------------------------------- frame conversion


def model_input(rig_slots: np.ndarray, state: VmcState) -> tuple[np.ndarray, np.ndarray]:
    """The avatar's frame as the session takes it: (Hips world position (3,), local rotations
    (J, 4) in the rig's order, the Hips' composed with the avatar root), mirrored to
    right-handed. `rig_slots`: the state slot of each rig joint, Hips first."""
    rot = _unit(state.rot[rig_slots]) * MIRROR_Q
    rq, rp = state.root_rot * MIRROR_Q, state.root_pos * MIRROR_P
    rot[0] = _qmul(rq, rot[0])
    return rp + _qapply(rq, state.pos[rig_slots[0]] * MIRROR_P), rot


def unity_output(state: VmcState, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `model_input` for a stylised frame: (Hips local position (3,), local
    rotations (J, 4)) in Unity axes, the avatar root taken out of the Hips again."""
    rq_inv = _qinv(state.root_rot * MIRROR_Q)
    rot = np.array(rotations, dtype=np.float64)
    rot[0] = _qmul(rq_inv, rot[0])
    hips = _qapply(rq_inv, np.asarray(root, dtype=np.float64) - state.root_pos * MIRROR_P)
    return hips * MIRROR_P, rot * MIRROR_Q


# --------------------------------------------------------------------------- the session


class SessionLike(Protocol):
    """What `StyleLink` needs of a session (`clients.sdk.Session`)."""

    def stylise(self, root: np.ndarray, rotations: np.ndarray) -> Any: ...  # -> .root (3,), .rotations (J, 4)
    def close(self) -> None: ...


OpenSession = Callable[[str], SessionLike]  # BVH header -> an open session on that rig


class StyleLink:
    """The bridge's session, owned by a worker thread so that the receive loop never waits on the
    network longer than `wait_s`.

    `stylise(header, root, rotations)` returns the stylised frame, or None when there is none to
    give in time: the session for `header` is still opening, the worker is busy (a late frame,
    a reconnect), or the call failed. A failed call (server restarted, resume token unknown,
    connection gone) drops the session and the worker opens a fresh one on the same rig, retrying
    with backoff (`retry_s`: first, most) until it succeeds; a new header (another avatar) opens
    a session on it. Meanwhile the bridge passes frames through."""

    def __init__(
        self, open_session: OpenSession, wait_s: float = 0.1, retry_s: tuple[float, float] = (0.05, 1.0)
    ) -> None:
        self.open_session, self.wait_s, self.retry_s = open_session, wait_s, retry_s
        self.sessions_opened = 0
        self.failures = 0
        self._cond = threading.Condition()
        self._session: SessionLike | None = None
        self._header: str | None = None  # the rig the open session serves
        self._want: str | None = None  # the rig a session is wanted for
        self._job: tuple | None = None
        self._result: tuple[int, tuple | None] = (-1, None)
        self._ticket = 0
        self._busy = False
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="vmc-style-link", daemon=True)
        self._thread.start()

    @property
    def ready(self) -> bool:
        return self._session is not None and self._header == self._want and not self._busy

    def wait_ready(self, timeout: float) -> bool:
        """Wait until a session serves the rig last asked for (tools and tests; the bridge never waits)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._want is not None and self.ready, timeout=timeout)

    def stylise(self, header: str, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        with self._cond:
            if header != self._want:
                self._want = header
                self._cond.notify_all()
            if self._busy or self._session is None or self._header != header:
                return None
            self._ticket += 1
            ticket = self._ticket
            self._job, self._busy = (ticket, root, rotations), True
            self._cond.notify_all()
            if not self._cond.wait_for(lambda: self._result[0] == ticket, timeout=self.wait_s):
                return None
            return self._result[1]

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout=5)
        self._drop()

    def _drop(self) -> None:
        session, self._session, self._header = self._session, None, None
        if session is not None:
            try:
                session.close()
            except Exception:  # noqa: BLE001 - a broken session may fail to close; it is gone either way
                pass

    def _run(self) -> None:
        delay = self.retry_s[0]
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._closed or self._job is not None or self._want != self._header)
                if self._closed:
                    return
                job, want = self._job, self._want
                if job is not None and want != self._header:  # the rig changed under a frame: no answer
                    self._job, self._result, self._busy, job = None, (job[0], None), False, None
                    self._cond.notify_all()
            if want != self._header:  # (re)open: the first rig, another avatar, or after a failure
                assert want is not None  # the worker wakes for a rig only once one is wanted
                self._drop()
                try:
                    opened = self.open_session(want)
                except Exception as exc:  # noqa: BLE001 - server down or refusing: retry later
                    log.warning("VMC bridge: no session yet (%s); frames pass through, retrying in %.2f s", exc, delay)
                    with self._cond:
                        self._cond.wait_for(lambda: self._closed, timeout=delay)
                    delay = min(2 * delay, self.retry_s[1])
                    continue
                with self._cond:
                    self._session, self._header, delay = opened, want, self.retry_s[0]
                    self.sessions_opened += 1
                    self._cond.notify_all()
                log.info("VMC bridge: session %d open", self.sessions_opened)
                continue
            current = self._session
            if job is None or current is None:
                continue
            ticket, root, rotations = job
            try:
                styled = current.stylise(root, rotations)
                result = (np.asarray(styled.root, dtype=np.float64), np.asarray(styled.rotations, dtype=np.float64))
            except Exception as exc:  # noqa: BLE001 - server restarted, token unknown, network gone
                self.failures += 1
                log.warning("VMC bridge: session lost (%s); frames pass through until a fresh one opens", exc)
                result = None
                self._drop()
            with self._cond:
                self._job, self._result, self._busy = None, (ticket, result), False
                self._cond.notify_all()


# --------------------------------------------------------------------------- the bridge


@dataclass
class BridgeStats:
    frames: int = 0  # frames sent on
    styled: int = 0  # of which stylised
    forwarded: int = 0  # datagrams passed on without a frame
    own_s: deque = field(default_factory=lambda: deque(maxlen=100_000))  # bridge time per frame, session wait excluded
    wait_s: deque = field(default_factory=lambda: deque(maxlen=100_000))  # time waiting for the session

    def summary(self, bad: int = 0, link: StyleLink | None = None) -> dict:
        own, wait = np.array(self.own_s) * 1e6, np.array(self.wait_s) * 1e6
        q = lambda a, p: round(float(np.percentile(a, p)), 1) if len(a) else None  # noqa: E731
        return {
            "frames": self.frames,
            "styled": self.styled,
            "forwarded": self.forwarded,
            "bad_datagrams": bad,
            "sessions_opened": link.sessions_opened if link else 0,
            "session_failures": link.failures if link else 0,
            "bridge_us_median": q(own, 50),
            "bridge_us_p99": q(own, 99),
            "session_us_median": q(wait, 50),
        }


class VmcBridge:
    """Receives VMC on `listen`, restyles the body bones in `bones` through `link` and sends the
    frame on to `send`. `handle(data, now)` is the whole per-datagram logic (datagrams out);
    `serve_forever()` runs it on a UDP socket (port 0: a free one, see `address`); `link=None`
    passes everything through."""

    def __init__(
        self,
        link: StyleLink | None,
        send: tuple[str, int] = ("127.0.0.1", 39540),
        listen: tuple[str, int] = ("127.0.0.1", 39539),
        bones: Iterable[str] = BODY_BONES,
        bone_timeout_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.link, self.send, self.clock = link, send, clock
        self.mask = frozenset(bones)
        self.state = VmcState(bone_timeout_s)
        self.receiver = VmcReceiver(self.state)
        self.stats = BridgeStats()
        self._bones = osc.PoseEncoder(BONE_ADDRESS)
        self._prefixes: list[bytes] = []  # each state slot's bone message prefix
        self._rig: AvatarRig | None = None
        self._rig_key: int | None = None
        self._rig_error: str | None = None
        self._rig_slots = np.zeros(0, int)
        self._restyled = np.zeros(0, bool)
        self._t0 = clock()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(listen)
        self.sock.settimeout(0.1)  # serve_forever looks at its stop flag this often
        self._stop = threading.Event()

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()[:2]

    @property
    def rig(self) -> AvatarRig | None:
        return self._rig

    def handle(self, data: bytes, now: float) -> list[bytes]:
        """Datagrams to send for one received: passed on as they came, or one restyled frame's."""
        t0 = time.perf_counter()
        got = self.receiver.feed(data, now)
        out = list(got.forward)
        self.stats.forwarded += len(got.forward)
        wait = 0.0
        for passed in got.frames:
            datagrams, w = self._frame(passed, now)
            out += datagrams
            wait += w
        if got.frames:  # the bridge's own time per frame: decode, convert, encode (the session wait apart)
            own = (time.perf_counter() - t0 - wait) / len(got.frames)
            self.stats.own_s.extend([own] * len(got.frames))
        return out

    def _current_rig(self) -> AvatarRig | None:
        """The avatar's rig: kept while the sender's body bones and their offsets stay the same,
        rebuilt when a bone appears or the offsets change (another avatar)."""
        from models.motion.humanoid import RigError

        state, rig = self.state, self._rig
        if self._rig_key == state.version:
            if rig is None:
                return None  # tried with these bones already; the error was logged
            if np.abs(state.pos[self._rig_slots[1:]] - rig.offsets[1:]).max(initial=0.0) <= 1e-4:
                return rig
        self._rig_key = state.version
        try:
            rig = avatar_rig(state.body())
        except RigError as err:
            if err.message != self._rig_error:
                log.warning("VMC bridge: passing frames through, the avatar cannot be restyled yet: %s", err.message)
            self._rig, self._rig_error = None, err.message
            return None
        self._rig, self._rig_error = rig, None
        self._rig_slots = np.array([state.slot[b] for b in rig.bones])
        self._restyled = np.array([b in self.mask for b in rig.bones])
        log.info("VMC bridge: avatar rig of %d body bones, leg %.3f m", len(rig.bones), rig.report["leg_length"])
        return rig

    def _frame(self, passed: list[bytes], now: float) -> tuple[list[bytes], float]:
        """The frame's datagrams, and the time spent waiting on the session."""
        state = self.state
        state.expire(now)
        rot, pos = state.rot, state.pos
        link = self.link
        rig = self._current_rig() if link is not None and self.mask else None
        wait = 0.0
        if rig is not None and link is not None:
            root, rotations = model_input(self._rig_slots, state)
            t1 = time.perf_counter()
            styled = link.stylise(rig.header, root, rotations)
            wait = time.perf_counter() - t1
            if styled is not None:
                hips, local = unity_output(state, *styled)
                rot, pos = rot.copy(), pos.copy()
                slots = self._rig_slots[self._restyled]
                rot[slots] = local[self._restyled]
                if self._restyled[0]:
                    pos[self._rig_slots[0]] = hips
                self.stats.styled += 1
        n = len(state.names)
        while len(self._prefixes) < n:
            self._prefixes.append(self._bones.prefix(state.names[len(self._prefixes)]))
        elements = [osc.element(state.root_message)] if state.root_message is not None else []
        elements += self._bones.join(self._prefixes, np.concatenate([pos[:n], rot[:n]], axis=1))
        elements += [osc.element(m) for m in passed]
        if not any(m.startswith(_OK_AT) for m in passed):
            elements.append(osc.element(osc.encode_message(OK_ADDRESS, [1])))
        if not any(m.startswith(_TIME_AT) for m in passed):
            elements.append(osc.element(osc.encode_message(TIME_ADDRESS, [float(now - self._t0)])))
        self.stats.frames += 1
        self.stats.wait_s.append(wait)
        return osc.bundles(elements), wait

    def serve_forever(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                raise
            for datagram in self.handle(data, self.clock()):
                self.sock.sendto(datagram, self.send)

    def start(self) -> threading.Thread:
        """Serve in a daemon thread."""
        thread = threading.Thread(target=self.serve_forever, name="vmc-bridge", daemon=True)
        thread.start()
        return thread

    def shutdown(self) -> None:
        self._stop.set()
        if self.link is not None:
            self.link.close()

    def close(self) -> None:
        self.shutdown()
        self.sock.close()


def session_opener(
    url: str,
    model: str,
    style: str,
    fps: float = 60.0,
    intensity: float = 1.0,
    token: str | None = None,
    timeout: float = 5.0,
    reconnect_timeout: float = 60.0,
) -> OpenSession:
    """Sessions of `clients.sdk` on an avatar rig (its BVH header). The SDK session reconnects by
    itself for `reconnect_timeout` s (resuming, or opening a fresh session when the server forgot
    its token); a reply later than `timeout` s, or a reconnect that gives up, ends it and the
    `StyleLink` opens a fresh one."""
    from .sdk import Client

    client = Client(url, token, timeout=timeout, reconnect_timeout=reconnect_timeout)

    def open_session(header: str) -> SessionLike:
        return client.session(model=model, style=style, skeleton=None, bvh_header=header, fps=fps, intensity=intensity)

    return open_session


@lru_cache(maxsize=8)
def first_style(url: str, model: str) -> str:
    from .sdk import Client

    return next(m.styles[0] for m in Client(url).models() if m.name == model)


# --------------------------------------------------------------------------- CLI


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", type=int, default=39539, help="UDP port to receive VMC on (default 39539)")
    p.add_argument("--listen-host", default="127.0.0.1", help="interface to receive on (0.0.0.0 for all)")
    p.add_argument("--send-host", default="127.0.0.1", help="where to send the restyled VMC")
    p.add_argument("--send-port", type=int, default=39540, help="port to send to (default 39540)")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="the stylestream server")
    p.add_argument("--token", help="API token, if the server wants one")
    p.add_argument("--model", default="lti")
    p.add_argument("--style", help="target style (default: the model's first)")
    p.add_argument("--intensity", type=float, default=1.0)
    p.add_argument("--fps", type=float, default=60.0, help="the sender's frame rate")
    p.add_argument(
        "--bones",
        default="body",
        help="bones to restyle: Unity names and groups (body, upper, lower, "
        "spine, head, arms, legs), '-Name' removes; the rest pass through (default: body)",
    )
    p.add_argument(
        "--bone-timeout",
        type=float,
        default=1.0,
        help="seconds after which a bone the sender stopped sending goes back to rest (default 1)",
    )
    p.add_argument(
        "--wait-ms",
        type=float,
        default=100.0,
        help="a frame the server has not answered within this passes through unstyled (default 100)",
    )
    p.add_argument("--stats", action="store_true", help="print the bridge's counters and timings as JSON on exit")


def add_vmc_command(sub) -> None:
    p = sub.add_parser("vmc", help="VMC (OSC/UDP) bridge: receive VMC, restyle the avatar, send VMC on")
    add_arguments(p)
    p.set_defaults(func=run_bridge)


def run_bridge(args: argparse.Namespace) -> int:
    import signal

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        bones = parse_bones(args.bones)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    style = args.style or first_style(args.url, args.model)
    link = StyleLink(
        session_opener(args.url, args.model, style, args.fps, args.intensity, args.token), args.wait_ms / 1000
    )
    bridge = VmcBridge(
        link, (args.send_host, args.send_port), (args.listen_host, args.listen), bones, args.bone_timeout
    )
    host, port = bridge.address
    print(
        f"VMC bridge: {host}:{port} -> {args.model}/{style} ({len(bones)} bones restyled) -> "
        f"{args.send_host}:{args.send_port} (Ctrl-C stops)",
        flush=True,
    )
    signal.signal(signal.SIGTERM, lambda *_: bridge._stop.set())
    try:
        bridge.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        bridge.close()
    summary = bridge.stats.summary(bridge.receiver.bad, link)
    print(
        json.dumps(summary)
        if args.stats
        else f"{summary['frames']} frames, {summary['styled']} restyled, {summary['sessions_opened']} session(s)",
        flush=True,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["bench"]:
        from .vmc_bench import main as bench

        return bench(argv[1:])
    p = argparse.ArgumentParser(
        prog="python -m clients.vmc", description="VMC bridge (or: python -m clients.vmc bench)"
    )
    add_arguments(p)
    return run_bridge(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
