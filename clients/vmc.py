"""VMC bridge: Virtual Motion Capture (OSC over UDP) in, stylised VMC out.

    stylestream vmc --listen 39539 --send-host 127.0.0.1 --send-port 39540 --model lti --style elderly

receives VMC protocol messages (`/VMC/Ext/Root/Pos` and `/VMC/Ext/Bone/Pos`, each
`name, px, py, pz, qx, qy, qz, qw`, with Unity `HumanBodyBones` names), maps the humanoid bones onto
the Bandai Namco (BN) skeleton every model uses, streams each frame through a session of the
service (`clients.sdk`) and sends the stylised pose on as VMC: one OSC bundle per frame holding
`/VMC/Ext/Root/Pos`, one `/VMC/Ext/Bone/Pos` per mapped bone, `/VMC/Ext/OK 1` and `/VMC/Ext/T time`.

Framing of the input: a frame is complete when an OSC bundle ends (the usual VMC sender puts a
whole frame in one bundle) or, for senders that send loose messages, when `/VMC/Ext/T` arrives.
Bone values persist between frames: a bone a sender does not send keeps its last value (identity
rotation and the rest offset until first seen), as in VMC receivers. Other VMC addresses
(blend shapes, trackers, `/VMC/Ext/OK`...) are ignored.

Assumptions (the mapping's contract)
------------------------------------
* **VMC side** (Unity): left-handed, Y up, metres. Bone transforms are *local* (relative to the
  Unity humanoid parent; `Hips` relative to the avatar root of `/VMC/Ext/Root/Pos`), and the
  avatar is *normalised*: in its T-pose every local rotation is identity and every bone frame is
  aligned with the world (what VRM avatars and VMC senders use). The T-pose faces +Z (Unity), arms
  along +-X, legs down, spine up.
* **Handedness**: Unity -> right-handed by mirroring the X axis: position `(x, y, z) -> (-x, y, z)`,
  quaternion `(x, y, z, w) -> (x, -y, -z, w)` (`unity_to_right_handed`; its inverse
  `right_handed_to_unity` is the same reflection). Units: metres * 100 = cm (`CM_PER_METRE`).
  After the mirror the avatar faces +Z with its left at +X, which is BN's world frame (Y up, cm).
* **BN side**: the 22-joint BN skeleton of `models.motion.assets.bandai_namco_pose()`, local
  quaternions scalar-last xyzw, `root` = the `Hips` translation (cm). BN has no T-pose (its bones
  lie along each joint's local +-X), so a per-joint *rest alignment* `A_j` (`build_vmc_rig`) is the
  BN global rotation that puts BN into the VMC T-pose: computed with
  `scipy.spatial.transform.Rotation.align_vectors`, the bone (the offset to the child that
  `models.motion.retarget` matches on; a leaf's own +-X) aligned exactly with its T-pose
  direction, the twist about it as close as possible to BN's natural standing pose (for `Hips`
  and `Chest`: the hip / shoulder line along +X). Feet and toes keep the natural pose's pitch
  (made left-right symmetric), since a T-pose stands flat-footed.
* **The mapping**: with `W_b` the VMC global rotation of bone b (product of Unity local rotations
  from the root, mirrored), `BN_global_j = W_b(j) * A_j`, BN locals follow from BN parents. The
  inverse is exact: `W = BN_global * A^-1`, VMC local = `W_parent^-1 * W`. A Unity `UpperChest`,
  if sent, is folded into BN `Chest` (BN has none); fingers, eyes, jaw are not mapped. BN's static
  `joint_Root` is the VMC root (`/VMC/Ext/Root/Pos`); `Hips` carries the translation. Bone
  positions sent out are the BN rest offsets in T-pose axes (metres); received ones are ignored
  except `Hips` and the root (the BN skeleton's proportions are fixed; no retargeting of avatar
  size is done).

Everything above is pure (numpy / scipy) and round-trips exactly: BN frame -> VMC frame ->
messages -> parsed -> BN frame. OSC itself carries float32, so over the wire values hold to
~1e-7 relative. The I/O (`VmcBridge`) is a thin python-osc loop: one receiving thread that, per
completed frame, converts, calls the session (blocking, one frame in, one frame out; frames that
arrive meanwhile wait in the UDP buffer) and sends the result.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from models.motion.rotations import quat_apply, quat_inv, quat_mul
from models.motion.skeleton import Motion, Skeleton, fk

log = logging.getLogger(__name__)

CM_PER_METRE = 100.0
ROOT_ADDRESS = "/VMC/Ext/Root/Pos"
BONE_ADDRESS = "/VMC/Ext/Bone/Pos"
OK_ADDRESS = "/VMC/Ext/OK"
TIME_ADDRESS = "/VMC/Ext/T"

# BN joint -> Unity HumanBodyBones name (joint_Root is the VMC root, not a bone).
BN_TO_UNITY: dict[str, str] = {
    "Hips": "Hips", "Spine": "Spine", "Chest": "Chest", "Neck": "Neck", "Head": "Head",
    **{f"{bn}_{s}": f"{side}{unity}" for s, side in (("L", "Left"), ("R", "Right")) for bn, unity in (
        ("Shoulder", "Shoulder"), ("UpperArm", "UpperArm"), ("LowerArm", "LowerArm"), ("Hand", "Hand"),
        ("UpperLeg", "UpperLeg"), ("LowerLeg", "LowerLeg"), ("Foot", "Foot"), ("Toes", "Toes"))},
}
UNITY_TO_BN: dict[str, str] = {u: b for b, u in BN_TO_UNITY.items()}

# Unity humanoid parent of each bone this bridge reads (None: child of the VMC root). Neck and the
# shoulders hang off UpperChest, which is identity when a sender has none.
UNITY_PARENTS: dict[str, str | None] = {
    "Hips": None, "Spine": "Hips", "Chest": "Spine", "UpperChest": "Chest", "Neck": "UpperChest", "Head": "Neck",
    **{f"{side}{b}": f"{side}{p}" if p != "UpperChest" else p for side in ("Left", "Right") for b, p in (
        ("Shoulder", "UpperChest"), ("UpperArm", "Shoulder"), ("LowerArm", "UpperArm"), ("Hand", "LowerArm"))},
    **{f"{side}{b}": f"{side}{p}" if p != "Hips" else p for side in ("Left", "Right") for b, p in (
        ("UpperLeg", "Hips"), ("LowerLeg", "UpperLeg"), ("Foot", "LowerLeg"), ("Toes", "Foot"))},
}
# The Unity bone whose global rotation drives a BN joint (Chest takes UpperChest's, which equals
# Chest's when the sender has no UpperChest).
_DRIVER = {**{b: u for b, u in BN_TO_UNITY.items()}, "Chest": "UpperChest"}

# T-pose directions in BN world axes (right-handed, Y up, facing +Z, left at +X). Feet and toes
# are filled in from the natural pose by `build_vmc_rig`.
_UP, _DOWN, _LEFT, _RIGHT = (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)
TPOSE_DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "Hips": _UP, "Spine": _UP, "Chest": _UP, "Neck": _UP, "Head": _UP,
    **{f"{b}_L": _LEFT for b in ("Shoulder", "UpperArm", "LowerArm", "Hand")},
    **{f"{b}_R": _RIGHT for b in ("Shoulder", "UpperArm", "LowerArm", "Hand")},
    **{f"{b}_{s}": _DOWN for b in ("UpperLeg", "LowerLeg") for s in "LR"},
}
# BN joint -> the child whose offset is its bone (as in models.motion.retarget); others are leaves.
_BONE_CHILD = {
    "Hips": "Spine", "Spine": "Chest", "Chest": "Neck", "Neck": "Head",
    **{f"{a}_{s}": f"{b}_{s}" for s in "LR" for a, b in (
        ("Shoulder", "UpperArm"), ("UpperArm", "LowerArm"), ("LowerArm", "Hand"),
        ("UpperLeg", "LowerLeg"), ("LowerLeg", "Foot"), ("Foot", "Toes"))},
}
# Joints with several children: (left child, right child) whose line lies along +X in the T-pose.
_LATERAL = {"Hips": ("UpperLeg_L", "UpperLeg_R"), "Chest": ("Shoulder_L", "Shoulder_R")}


# --------------------------------------------------------------------------- handedness

def unity_to_right_handed(position: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unity (left-handed, Y up) -> right-handed Y-up axes by mirroring X.

    position (..., 3) `(x, y, z) -> (-x, y, z)`; rotation (..., 4) xyzw `(x, y, z, w) -> (x, -y, -z, w)`
    (the reflection M maps a rotation R to M R M). Units are unchanged. Inverse:
    `right_handed_to_unity`."""
    p = np.array(position, dtype=np.float64)
    q = np.array(rotation, dtype=np.float64)
    p[..., 0] *= -1.0
    q[..., 1:3] *= -1.0
    return p, q


def right_handed_to_unity(position: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `unity_to_right_handed` (a reflection is its own inverse)."""
    return unity_to_right_handed(position, rotation)


# --------------------------------------------------------------------------- the rig

@dataclass(frozen=True)
class VmcRig:
    """What maps BN frames to and from VMC: the BN skeleton, per joint the BN global rotation in
    the VMC T-pose (`alignment`, (J, 4) xyzw, identity for joint_Root) and the local position of
    each joint in T-pose axes (`tpose_offsets`, (J, 3), right-handed cm), which is what VMC's bone
    positions carry."""

    skeleton: Skeleton
    alignment: np.ndarray
    tpose_offsets: np.ndarray

    @property
    def bones(self) -> list[str]:
        """Unity names of the mapped bones, in BN joint order."""
        return [BN_TO_UNITY[n] for n in self.skeleton.names if n in BN_TO_UNITY]


def _yaw_to_face_z(skeleton: Skeleton, g_rot: np.ndarray, g_pos: np.ndarray) -> np.ndarray:
    """Quaternion about +Y turning a pose so that it faces +Z (left = hip line, forward = left x up)."""
    left = g_pos[skeleton.index("UpperLeg_L")] - g_pos[skeleton.index("UpperLeg_R")]
    forward = np.cross(left, [0.0, 1.0, 0.0])
    angle = np.arctan2(forward[0], forward[2])
    return Rotation.from_rotvec([0.0, -angle, 0.0]).as_quat()


def _bone_vector(skeleton: Skeleton, name: str) -> np.ndarray:
    """The joint's bone in its own frame: the offset of its matched child, or for a leaf (Head,
    Hand, Toes) its own +-X (BN's right side points along -X)."""
    if name in _BONE_CHILD:
        v = skeleton.offsets[skeleton.index(_BONE_CHILD[name])]
    else:
        v = np.array([np.sign(skeleton.offsets[skeleton.index(name)][0]) or 1.0, 0.0, 0.0])
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


def tpose_alignment(pose: Motion, frame: int = 0) -> np.ndarray:
    """BN global rotations (J, 4) that put the BN skeleton into the VMC T-pose, in BN world axes.

    Per joint, `Rotation.align_vectors` maps the joint's bone exactly onto its T-pose direction
    (`TPOSE_DIRECTIONS`; feet and toes: the natural pose's direction made left-right symmetric)
    and keeps the twist about it as close as it can to the natural pose `pose[frame]` turned to
    face +Z; for Hips and Chest the hip / shoulder line goes along +X instead. joint_Root: identity.
    """
    sk = pose.skeleton
    g_rot, g_pos = fk(pose.rotations[frame], pose.translations[frame], sk.parents)
    yaw = _yaw_to_face_z(sk, g_rot, g_pos)
    natural = quat_mul(yaw, g_rot)  # (J, 4) natural globals facing +Z
    directions = {k: np.array(v) for k, v in TPOSE_DIRECTIONS.items()}
    for bone in ("Foot", "Toes"):
        left = quat_apply(natural[sk.index(f"{bone}_L")], _bone_vector(sk, f"{bone}_L"))
        right = quat_apply(natural[sk.index(f"{bone}_R")], _bone_vector(sk, f"{bone}_R"))
        d = 0.5 * (left + right * [-1.0, 1.0, 1.0])
        d[0] = 0.0
        directions[f"{bone}_L"] = directions[f"{bone}_R"] = d / np.linalg.norm(d)
    out = np.tile([0.0, 0.0, 0.0, 1.0], (sk.num_joints, 1))
    for j, name in enumerate(sk.names):
        if name not in BN_TO_UNITY:
            continue
        bone = _bone_vector(sk, name)
        if name in _LATERAL:
            a, b = _LATERAL[name]
            lateral = sk.offsets[sk.index(a)] - sk.offsets[sk.index(b)]
            targets, sources = [directions[name], [1.0, 0.0, 0.0]], [bone, lateral]
        else:
            axes = np.eye(3)[1:]  # keep local Y and Z near where the natural pose has them
            targets, sources = [directions[name], *quat_apply(natural[j], axes)], [bone, *axes]
        rot, _ = Rotation.align_vectors(targets, sources, weights=[np.inf] + [1.0] * (len(sources) - 1))
        out[j] = rot.as_quat()
    return out


def build_vmc_rig(pose: Motion | None = None) -> VmcRig:
    """The rig for a BN skeleton (default: the committed BN pose asset, `default_vmc_rig`)."""
    if pose is None:
        from models.motion.assets import bandai_namco_pose

        pose = bandai_namco_pose()
    sk = pose.skeleton
    missing = [n for n in ("joint_Root", *BN_TO_UNITY) if n not in sk.names]
    if missing:
        raise ValueError(f"not a Bandai Namco skeleton (missing {', '.join(missing)})")
    alignment = tpose_alignment(pose)
    offsets = np.array(sk.offsets, dtype=np.float64)
    for j, p in enumerate(sk.parents):
        if p >= 0:
            offsets[j] = quat_apply(alignment[p], offsets[j])
    return VmcRig(sk, alignment, offsets)


@lru_cache(maxsize=1)
def default_vmc_rig() -> VmcRig:
    return build_vmc_rig()


# --------------------------------------------------------------------------- BN <-> VMC frames

@dataclass
class VmcFrame:
    """One VMC frame in Unity conventions (left-handed, metres, xyzw): the avatar root and, per
    Unity bone name, its local (position (3,), rotation (4,))."""

    root_position: np.ndarray
    root_rotation: np.ndarray
    bones: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


def bn_to_vmc(root: np.ndarray, rotations: np.ndarray, rig: VmcRig | None = None) -> VmcFrame:
    """A BN frame (Hips translation (3,) cm, local rotations (J, 4) xyzw) -> VMC frame.

    `W = BN_global * A^-1` per joint; a bone's VMC rotation is `W_parent^-1 * W`, joint_Root's
    global rotation is the VMC root's. Positions: the root at joint_Root's offset, Hips at
    `root`, other bones at their T-pose offsets; all mirrored to Unity and in metres."""
    rig = rig or default_vmc_rig()
    sk = rig.skeleton
    rotations = np.asarray(rotations, dtype=np.float64)
    rotations = rotations / np.linalg.norm(rotations, axis=-1, keepdims=True)
    translations = np.array(rig.tpose_offsets)
    translations[sk.index("Hips")] = root
    g_rot, _ = fk(rotations, translations, sk.parents)
    world = quat_mul(g_rot, quat_inv(rig.alignment))
    r0 = sk.index("joint_Root")
    root_pos, root_rot = right_handed_to_unity(sk.offsets[r0] / CM_PER_METRE, world[r0])
    frame = VmcFrame(root_pos, root_rot)
    for j, name in enumerate(sk.names):
        if name not in BN_TO_UNITY:
            continue
        local = quat_mul(quat_inv(world[sk.parents[j]]), world[j])
        frame.bones[BN_TO_UNITY[name]] = right_handed_to_unity(translations[j] / CM_PER_METRE, local)
    return frame


def vmc_to_bn(frame: VmcFrame, rig: VmcRig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A VMC frame -> BN frame (Hips translation (3,) cm, local rotations (J, 4) xyzw).

    Unity globals `W` from the humanoid hierarchy (missing bones: identity), `BN_global = W * A`,
    BN locals from BN parents. The Hips translation is the VMC Hips position expressed under BN's
    joint_Root (which takes the VMC root's rotation). Inverse of `bn_to_vmc`."""
    rig = rig or default_vmc_rig()
    sk = rig.skeleton
    root_pos, root_rot = unity_to_right_handed(frame.root_position, frame.root_rotation)
    root_pos = root_pos * CM_PER_METRE
    world: dict[str | None, np.ndarray] = {None: root_rot / np.linalg.norm(root_rot)}
    for bone, parent in UNITY_PARENTS.items():  # parents first
        if bone in frame.bones:
            _, q = unity_to_right_handed(np.zeros(3), frame.bones[bone][1])
            q = q / np.linalg.norm(q)
        else:
            q = np.array([0.0, 0.0, 0.0, 1.0])
        world[bone] = quat_mul(world[parent], q)
    g_rot = np.empty((sk.num_joints, 4))
    for j, name in enumerate(sk.names):
        w = world[_DRIVER[name]] if name in _DRIVER else world[None]
        g_rot[j] = quat_mul(w, rig.alignment[j])
    local = np.array(g_rot)
    for j, p in enumerate(sk.parents):
        if p >= 0:
            local[j] = quat_mul(quat_inv(g_rot[p]), g_rot[j])
    hips, r0 = sk.index("Hips"), sk.index("joint_Root")
    if "Hips" in frame.bones:
        hips_pos = unity_to_right_handed(frame.bones["Hips"][0], np.array([0.0, 0.0, 0.0, 1.0]))[0] * CM_PER_METRE
    else:
        hips_pos = rig.tpose_offsets[hips]
    root = hips_pos + quat_apply(quat_inv(local[r0]), root_pos - sk.offsets[r0])
    return root, local


# --------------------------------------------------------------------------- messages

Message = tuple[str, list]


def vmc_messages(frame: VmcFrame, t: float | None = None) -> list[Message]:
    """A VMC frame -> the (address, arguments) messages of one VMC frame: Root/Pos, a Bone/Pos per
    bone, `/VMC/Ext/OK 1` and, if given, `/VMC/Ext/T t`."""
    def args(name: str, p: np.ndarray, q: np.ndarray) -> list:
        return [name, *(float(v) for v in p), *(float(v) for v in q)]

    out: list[Message] = [(ROOT_ADDRESS, args("root", frame.root_position, frame.root_rotation))]
    out += [(BONE_ADDRESS, args(name, p, q)) for name, (p, q) in frame.bones.items()]
    out.append((OK_ADDRESS, [1]))
    if t is not None:
        out.append((TIME_ADDRESS, [float(t)]))
    return out


def apply_message(frame: VmcFrame, address: str, args: Sequence) -> bool:
    """Update `frame` in place from one VMC message; True if it was a root or bone message."""
    if address not in (ROOT_ADDRESS, BONE_ADDRESS) or len(args) < 8:
        return False
    p, q = np.array(args[1:4], dtype=np.float64), np.array(args[4:8], dtype=np.float64)
    if address == ROOT_ADDRESS:
        frame.root_position, frame.root_rotation = p, q
    else:
        frame.bones[str(args[0])] = (p, q)
    return True


def parse_vmc_messages(messages: Sequence[Message], previous: VmcFrame | None = None) -> VmcFrame:
    """Messages -> VMC frame, starting from `previous` (values a sender leaves out persist)."""
    frame = _copy_frame(previous) if previous is not None else _rest_frame()
    for address, args in messages:
        apply_message(frame, address, args)
    return frame


def _rest_frame() -> VmcFrame:
    return VmcFrame(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))


def _copy_frame(frame: VmcFrame) -> VmcFrame:
    return VmcFrame(np.array(frame.root_position), np.array(frame.root_rotation), dict(frame.bones))


# --------------------------------------------------------------------------- OSC I/O

def build_bundle(messages: Sequence[Message]):
    """One OSC bundle (sent immediately) holding the messages."""
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message_builder import OscMessageBuilder

    builder = OscBundleBuilder(IMMEDIATELY)
    for address, args in messages:
        msg = OscMessageBuilder(address=address)
        for a in args:
            msg.add_arg(a)
        builder.add_content(msg.build())
    return builder.build()


class VmcReceiver:
    """Assembles VMC frames from OSC packets and calls `on_frame(frame, messages)` per frame.

    `dispatcher` is a python-osc Dispatcher for any python-osc server: a frame completes when a
    bundle ends, or on `/VMC/Ext/T` outside a bundle."""

    def __init__(self, on_frame: Callable[[VmcFrame, list[Message]], None]) -> None:
        from pythonosc import dispatcher as osc_dispatcher
        from pythonosc import osc_bundle, osc_packet

        self.on_frame = on_frame
        self.frame = _rest_frame()
        self._pending: list[Message] = []
        self._in_bundle = False
        receiver = self

        class _Dispatcher(osc_dispatcher.Dispatcher):
            def call_handlers_for_packet(self, data: bytes, client_address) -> list:  # noqa: D401
                try:
                    packet = osc_packet.OscPacket(data)
                except osc_packet.ParseError:
                    return []
                receiver._in_bundle = osc_bundle.OscBundle.dgram_is_bundle(data)
                for timed in packet.messages:
                    for handler in self.handlers_for_address(timed.message.address):
                        handler.invoke(client_address, timed.message)
                if receiver._in_bundle:
                    receiver._in_bundle = False
                    receiver._complete()
                return []

        self.dispatcher = _Dispatcher()
        self.dispatcher.map(ROOT_ADDRESS, self._pose)
        self.dispatcher.map(BONE_ADDRESS, self._pose)
        self.dispatcher.map(TIME_ADDRESS, self._time)

    def _pose(self, address: str, *args) -> None:
        if apply_message(self.frame, address, args):
            self._pending.append((address, list(args)))

    def _time(self, address: str, *args) -> None:
        self._pending.append((address, list(args)))
        if not self._in_bundle:
            self._complete()

    def _complete(self) -> None:
        if not any(a in (ROOT_ADDRESS, BONE_ADDRESS) for a, _ in self._pending):
            self._pending = []
            return
        messages, self._pending = self._pending, []
        self.on_frame(_copy_frame(self.frame), messages)


Stylise = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


class VmcBridge:
    """Receives VMC on (listen_host, listen_port), stylises each frame with `stylise(root,
    rotations) -> (root, rotations)` (BN frames) and sends the result as one VMC bundle per frame
    to (send_host, send_port). Port 0 picks a free port (`address`). Run `serve_forever()` (in a
    thread if you like) and stop it with `shutdown()`."""

    def __init__(self, stylise: Stylise, send_host: str = "127.0.0.1", send_port: int = 39540,
                 listen_host: str = "127.0.0.1", listen_port: int = 39539, rig: VmcRig | None = None) -> None:
        from pythonosc import osc_server, udp_client

        self.stylise, self.rig = stylise, rig or default_vmc_rig()
        self.receiver = VmcReceiver(self._on_frame)
        self.server = osc_server.BlockingOSCUDPServer((listen_host, listen_port), self.receiver.dispatcher)
        self.client = udp_client.SimpleUDPClient(send_host, send_port)
        self.frames = 0
        self.errors = 0
        self._previous: np.ndarray | None = None
        self._t0 = time.monotonic()

    @property
    def address(self) -> tuple[str, int]:
        return self.server.server_address[:2]

    def _on_frame(self, frame: VmcFrame, messages: list[Message]) -> None:
        root, rotations = vmc_to_bn(frame, self.rig)
        if self._previous is not None:  # keep quaternion hemispheres continuous for the model
            rotations = np.where(np.sum(rotations * self._previous, axis=-1, keepdims=True) < 0, -rotations, rotations)
        self._previous = rotations
        try:
            out_root, out_rot = self.stylise(root, rotations)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the bridge
            self.errors += 1
            log.warning("frame not stylised: %s", exc)
            return
        out = bn_to_vmc(np.asarray(out_root), np.asarray(out_rot), self.rig)
        self.client.send(build_bundle(vmc_messages(out, time.monotonic() - self._t0)))
        self.frames += 1

    def serve_forever(self) -> None:
        self.server.serve_forever(poll_interval=0.05)

    def shutdown(self) -> None:
        self.server.shutdown()
        self.server.server_close()

    def start(self) -> threading.Thread:
        """Serve in a daemon thread."""
        thread = threading.Thread(target=self.serve_forever, name="vmc-bridge", daemon=True)
        thread.start()
        return thread


def session_stylise(session) -> Stylise:
    """Adapt a `clients.sdk.Session` to the bridge's `stylise(root, rotations)`."""
    def stylise(root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        styled = session.stylise(root, rotations)
        return styled.root, styled.rotations

    return stylise


# --------------------------------------------------------------------------- CLI

def add_vmc_command(sub) -> None:
    p = sub.add_parser("vmc", help="VMC (OSC/UDP) bridge: receive VMC, stylise, send VMC on")
    p.add_argument("--listen", type=int, default=39539, help="UDP port to receive VMC on (default 39539)")
    p.add_argument("--listen-host", default="127.0.0.1", help="interface to receive on (0.0.0.0 for all)")
    p.add_argument("--send-host", default="127.0.0.1", help="where to send the stylised VMC")
    p.add_argument("--send-port", type=int, default=39540, help="port to send to (default 39540)")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="the stylestream server")
    p.add_argument("--model", default="lti")
    p.add_argument("--style", help="target style (default: the model's first)")
    p.add_argument("--intensity", type=float, default=1.0)
    p.add_argument("--fps", type=float, default=60.0, help="the sender's frame rate (informational)")
    p.set_defaults(func=_vmc)


def _vmc(args: argparse.Namespace) -> int:
    from .sdk import Client

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    client = Client(args.url)
    style = args.style or next(m.styles[0] for m in client.models() if m.name == args.model)
    with client.session(model=args.model, style=style, fps=args.fps, intensity=args.intensity) as session:
        bridge = VmcBridge(session_stylise(session), args.send_host, args.send_port, args.listen_host, args.listen)
        host, port = bridge.address
        print(f"VMC bridge: {host}:{port} -> {args.model}/{style} -> {args.send_host}:{args.send_port} (Ctrl-C stops)")
        try:
            bridge.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            bridge.server.server_close()
        print(f"{bridge.frames} frames stylised, {bridge.errors} errors")
    return 0
