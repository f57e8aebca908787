"""Retargeting humanoid motions (any rig `humanoid` matches) onto the Bandai Namco (BN) skeleton.

BN's all-zero pose is no T-pose (it points the legs up the spine), so the mapping is built from
bone *directions*, never from either rest pose:

1. Each BN limb bone takes the direction of a client segment between two role joints
   (`humanoid.match_roles`, `humanoid.bn_segments`); each trunk bone the client's hips-head
   chain between BN's shares of its length (`retarget_stream.trunk_bones`), and each clavicle
   the direction BN's neutral data give it for the upper arm's (`retarget_clavicle`): rigs place
   spine, neck and collar joints differently, and copied joint by joint a CMU or Xia neutral
   walk's clavicles and neck lay far outside BN's neutral range.
2. Hips and Chest get two-vector frames: the bone up the spine and the line between the legs /
   upper arms (the hips' line as the client's rest pose holds it, `retarget_stream._rest_side`).
3. Every other joint (`TwistPlan`): its natural BN local rotation under the new BN parent, swung
   onto its segment; the twist follows the parent, never the client's own twist. Limb roots take
   the twist that lays BN's hinge axis along the client's limb plane (`HINGE_FALLBACK` when the
   limb is near straight). Leaves keep the natural local rotation.
   The hinge child (knee, elbow) bends about BN's hinge axis alone, as BN's own knees and elbows
   do (their off-axis rotation in the data is under 0.01 rad): where the chosen axis is not the
   client's limb plane (a fallback share), the lower bone is laid into BN's hinge plane and the
   limb turned so that its end keeps the client's direction (Unreal's pole-vector IK). Copied
   off-axis, the bend reached 0.08 rad on a Xia walk, eight standard deviations outside what the
   models were trained on.
   The foot bone takes the client's ankle-toe segment turned by the two rigs' flat-foot pitches
   where the client's rest pose stands (`retarget_stream._sole_terms`).
4. The Hips translation is scaled by the leg-length ratio and shifted so the toes on the ground
   sit at BN's toe height (`contact_height`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from .bn_skeleton import PRIMARY_CHILD, missing_joints
from .humanoid import HumanoidRig
from .resample import resample
from .retarget_clavicle import CLAVICLE_FROM_ARM
from .rotations import quat_canonical
from .skeleton import Motion, Skeleton, depths, fk, travel_on

# Joints with several children: (left child, right child) fixing the twist of the up vector.
# The client side takes the vector between its upper legs / upper arms (CMU collars sit on the
# spine, so the chest's left-right vector is taken between the shoulder joints).
_LATERAL = {"Hips": ("UpperLeg_L", "UpperLeg_R"), "Chest": ("Shoulder_L", "Shoulder_R")}


@dataclass(frozen=True)
class Rig:
    """A retargeting target: the skeleton, a natural pose that fixes limb twist, and floor height."""

    skeleton: Skeleton
    pose: np.ndarray  # (J, 4) local rotations of a natural (standing or walking) pose
    floor: float  # toe height on the ground in the target's data (`contact_height`, target units)
    euler_orders: tuple[str, ...] = ()  # per joint, for writing BVH like the target's files
    foot_pitch: float | None = None  # the ankle-toe bones' fall (radians) on a flat foot (`flat_foot_pitch`)

    @classmethod
    def from_motion(cls, motion: Motion, frame: int = 0) -> Rig:
        sk = motion.skeleton
        missing = missing_joints(sk.names)
        if missing:
            raise ValueError(f"not a Bandai Namco skeleton (missing {', '.join(missing)})")
        pos = motion.global_positions()
        toes, ankles = [sk.index("Toes_L"), sk.index("Toes_R")], [sk.index("Foot_L"), sk.index("Foot_R")]
        floor = contact_height(pos[:, toes, 1])
        pitch = flat_foot_pitch(sk, contact_height(pos[:, ankles, 1]), floor)
        return cls(sk, np.array(motion.rotations[frame], dtype=float), floor, tuple(motion.euler_orders), pitch)


def flat_foot_pitch(skeleton: Skeleton, ankle_floor: float, toe_floor: float) -> float:
    """How far (radians below level) a BN skeleton's ankle-toe bones fall on a flat foot: the
    ankle and toe joints at their heights on the ground. Rigs place these joints differently above
    the sole (BN's bone falls 40 degrees, CMU's and Xia's about 10): `retarget_stream._sole_terms`."""
    length = np.mean([np.linalg.norm(skeleton.offsets[skeleton.index(f"Toes_{s}")]) for s in "LR"])
    return float(np.arcsin(np.clip((ankle_floor - toe_floor) / length, -1.0, 1.0)))


def contact_height(toe_heights: np.ndarray, percentile: float = 5.0) -> float:
    """Toe height when on the ground: a low percentile of the lowest toe per frame (F, 2). Robust
    to single-frame dips in the data, and still the contact height for runs and jumps."""
    return float(np.percentile(np.asarray(toe_heights).min(axis=-1), percentile))


@lru_cache(maxsize=1)
def default_rig() -> Rig:
    """The BN rig from the committed asset (first frame of Bandai Namco data set 2's first normal
    walk, and that clip's toe floor), so retargeting needs no data at serving time."""
    from .assets import BANDAI_NAMCO_ANKLE_FLOOR, BANDAI_NAMCO_TOE_FLOOR, bandai_namco_pose

    pose, toe = bandai_namco_pose(), BANDAI_NAMCO_TOE_FLOOR
    pitch = flat_foot_pitch(pose.skeleton, BANDAI_NAMCO_ANKLE_FLOOR, toe)
    return Rig(pose.skeleton, np.array(pose.rotations[0], dtype=float), toe, tuple(pose.euler_orders), pitch)


def _frame(primary: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """Orthonormal frames (..., 3, 3) with columns (primary, lateral made orthogonal, their cross)."""
    e1 = primary / np.linalg.norm(primary, axis=-1, keepdims=True)
    e2 = lateral - np.sum(lateral * e1, axis=-1, keepdims=True) * e1
    e2 = e2 / np.linalg.norm(e2, axis=-1, keepdims=True)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=-1)


# BN limb joint -> its hinge child: the limb joint's twist is set by the plane of the limb
# (hip-knee-ankle, shoulder-elbow-wrist), so the hinge bends about the BN hinge axis.
_HINGES = {
    "UpperLeg_L": "LowerLeg_L",
    "UpperLeg_R": "LowerLeg_R",
    "UpperArm_L": "LowerArm_L",
    "UpperArm_R": "LowerArm_R",
}
# How much a near-straight limb falls back: the hinge axis aims along |n| n + HINGE_FALLBACK^2 f,
# n = cross(upper bone, lower bone) (|n| the sine of the bend), so the limb plane decides once
# the limb is well bent and a straighter limb turns smoothly to f. An axis weighted by (n . f)
# would flip as the plane crosses a quarter turn from f. f is the unit mean of BN's natural hinge
# axis and the client's own hinge axis, learned per stream in the frame of the joint carrying the
# hinge child: each frame's n weighted by sin^2 of its bend (a straight limb's plane is noise).
HINGE_FALLBACK = 0.6
# The weight of the stream's first natural axis in the learned axis, against sin^2 of each bend:
# a stream that never bends a limb keeps BN's twist following the client's.
HINGE_PRIOR = 1.0


# BN clavicles: laid by the upper arm's direction in the chest's frame, as BN's neutral data
# relate them (`retarget_clavicle`), not by the client's collar segment.
_CLAVICLES = tuple(CLAVICLE_FROM_ARM)


# The share of the chest's twist about the spine bone that BN's Spine takes, as Unity's humanoid
# spreads a twist over a chain: without it the whole spine twist lands in BN's Chest and jitters.
TWIST_SHARE = 0.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class TwistPlan:
    """How BN's global rotations follow from client bone directions (module docstring, step 3):
    the joints depth by depth, parents first, grouped by kind ("swing", "clavicle", "limb", "leaf"; Hips
    and Chest are the caller's two-vector frames). `segments` lists the BN joints whose bone
    direction the caller gives, in the order of its columns; the others are leaves.
    `retarget_stream.FrameRetargeter` compiles the groups into `retarget_kernels`' plan.
    """

    def __init__(self, rig: Rig, segments: tuple[str, ...]):
        sk = rig.skeleton
        col = {n: i for i, n in enumerate(segments)}
        self.segments = tuple(segments)
        self.num_joints = sk.num_joints
        self.lateral = np.array([sk.index(n) for n in _LATERAL])
        nat = Rotation.from_quat(rig.pose).as_matrix()  # (J, 3, 3) natural local rotations

        def off(n: str) -> np.ndarray:
            return sk.offsets[sk.index(n)]

        def kind_of(n: str) -> str:
            if n not in col:
                return "leaf"
            if n in _HINGES and _HINGES[n] in col:
                return "limb"
            return "clavicle" if n in _CLAVICLES else "swing"

        depth = depths(sk.parents)
        self.groups: list[dict] = []
        for d in range(1, int(depth.max()) + 1):
            level = [sk.names[j] for j in range(sk.num_joints) if depth[j] == d and sk.names[j] not in _LATERAL]
            for kind in ("swing", "clavicle", "limb", "leaf"):
                names = [n for n in level if kind_of(n) == kind]
                if not names:
                    continue
                js = np.array([sk.index(n) for n in names])
                g = {"kind": kind, "j": js, "p": sk.parents[js], "nat": nat[js]}
                if kind in ("swing", "clavicle", "limb"):
                    g["b"] = np.stack([_unit(off(PRIMARY_CHILD[n])) for n in names])
                    g["dir"] = np.array([col[n] for n in names])
                if kind == "swing" and any(PRIMARY_CHILD[n] in _LATERAL for n in names):
                    (n,) = names  # the spine: one joint under Hips, the Chest above it
                    c = sk.index(PRIMARY_CHILD[n])
                    g["split"] = (c, nat[c])
                if kind == "clavicle":  # read the upper arm's direction: (A | c) maps it (`retarget_clavicle`)
                    g["dir"] = np.array([col[PRIMARY_CHILD[n]] for n in names])
                    g["ac"] = np.array([CLAVICLE_FROM_ARM[n] for n in names], dtype=float)
                if kind == "limb":
                    hinge = [_HINGES[n] for n in names]
                    g["dir_c"] = np.array([col[h] for h in hinge])
                    g["h"] = np.array([list(_HINGES).index(n) for n in names])  # the hinge's row in a stream's state
                    # the natural bend's axis in the limb joint's frame: cross(upper bone, lower bone)
                    k = np.stack([_unit(np.cross(off(h), nat[sk.index(h)] @ off(PRIMARY_CHILD[h]))) for h in hinge])
                    g["k"] = k
                    g["m_loc_t"] = np.swapaxes(_frame(g["b"], k), -1, -2)
                    # lower bone length over upper: where the limb's end points (`_hinged`)
                    g["reach"] = np.array(
                        [np.linalg.norm(off(PRIMARY_CHILD[h])) / np.linalg.norm(off(h)) for h in hinge]
                    )
                self.groups.append(g)


def retarget(
    motion: Motion, target: Rig | Motion | None = None, fps: float = 30.0, source: HumanoidRig | None = None
) -> Motion:
    """A humanoid motion (any rig `humanoid` matches; CMU and Xia files included) as a BN-skeleton
    motion at `fps`: the per-frame mapping of `retarget_stream.FrameRetargeter` over the clip,
    with the Hips height set so that the clip's toe contact height (`contact_height`, which looks
    at the whole clip) is the target's.

    `target` is a `Rig`, a BN `Motion` (its first frame and toe heights make the rig) or None for
    `default_rig()`; `source` the matched client rig (default: matched from the motion's names).
    The result has the target's joints in the target's order; every translation is the target
    offset except Hips, which carries the scaled root motion.
    """
    from .retarget_stream import FrameRetargeter

    rig = default_rig() if target is None else target if isinstance(target, Rig) else Rig.from_motion(target)
    fr = FrameRetargeter(source if source is not None else motion.skeleton, rig)
    # the rig's frames carry one translation: any travel on joints above it moves onto it
    src = travel_on(resample(motion, fps), fr.humanoid.translated)
    sk, n = rig.skeleton, src.num_frames
    trans = np.broadcast_to(sk.offsets, (n, sk.num_joints, 3)).copy()
    if not n:
        return Motion(
            sk, np.zeros((0, sk.num_joints, 4)), trans, float(fps), rig.euler_orders or tuple("ZXY" for _ in sk.names)
        )
    hips_t, local = fr.to_model(src.translations[:, fr.humanoid.translated], src.rotations)
    hips = sk.index("Hips")
    trans[:, hips] = hips_t
    _, pos = fk(local, trans, sk.parents)
    toes = [sk.index("Toes_L"), sk.index("Toes_R")]
    trans[:, hips, 1] += rig.floor - contact_height(pos[:, toes, 1])
    return Motion(sk, quat_canonical(local), trans, float(fps), rig.euler_orders or tuple("ZXY" for _ in sk.names))
