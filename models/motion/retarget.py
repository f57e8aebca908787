"""Retargeting humanoid motions (any rig `humanoid` matches) onto the Bandai Namco (BN) skeleton.

BN's all-zero pose is no T-pose, so the mapping is built from bone *directions*, never rest poses:

1. Each BN limb bone takes a client segment's direction (`humanoid.bn_segments`); trunk bones
   the hips-head chain by length (`retarget_stream.trunk_bones`); clavicles follow the upper arm
   (`retarget_clavicle`): rigs place spine, neck and collar joints differently.
2. Hips and Chest get two-vector frames (up the spine, across the legs / upper arms).
3. Every other joint (`TwistPlan`): its natural BN rotation swung onto its segment, the twist
   following the parent; limbs bend about BN's hinge axis alone, as in BN's data, turned so the
   limb's end keeps the client's direction. Feet are pitched by the rigs' flat-foot pitches.
4. The Hips translation is scaled by the leg-length ratio, toes put at BN's height (`contact_height`).
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

# Joints with several children: (left child, right child) fixing the twist of the up vector
# (the client's upper legs / upper arms: CMU collars sit on the spine).
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
    """Radians below level a BN skeleton's ankle-toe bones fall on a flat foot."""
    length = np.mean([np.linalg.norm(skeleton.offsets[skeleton.index(f"Toes_{s}")]) for s in "LR"])
    return float(np.arcsin(np.clip((ankle_floor - toe_floor) / length, -1.0, 1.0)))


def contact_height(toe_heights: np.ndarray, percentile: float = 5.0) -> float:
    """Toe height on the ground: a low percentile of the lowest toe per frame (F, 2), robust to dips."""
    return float(np.percentile(np.asarray(toe_heights).min(axis=-1), percentile))


@lru_cache(maxsize=1)
def default_rig() -> Rig:
    """The BN rig from the committed asset, so retargeting needs no data at serving time."""
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


# BN limb joint -> its hinge child: the limb plane sets the limb joint's twist.
_HINGES = {
    "UpperLeg_L": "LowerLeg_L",
    "UpperLeg_R": "LowerLeg_R",
    "UpperArm_L": "LowerArm_L",
    "UpperArm_R": "LowerArm_R",
}
# How much a near-straight limb falls back: the hinge axis aims along |n| n + HINGE_FALLBACK^2 f,
# n = cross(upper bone, lower bone), so a bent limb's plane decides and a straighter one turns
# smoothly to f: the unit mean of BN's natural axis and the client's, learned per stream.
HINGE_FALLBACK = 0.6
# The weight of the stream's first natural axis in the learned axis, against sin^2 of each bend.
HINGE_PRIOR = 1.0


# BN clavicles: laid by the upper arm's direction in the chest's frame (`retarget_clavicle`).
_CLAVICLES = tuple(CLAVICLE_FROM_ARM)


# The share of the chest's twist BN's Spine takes (as Unity's humanoid): else the Chest jitters.
TWIST_SHARE = 0.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class TwistPlan:
    """How BN's global rotations follow from client bone directions (module docstring, step 3)."""

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
    """A humanoid motion as a BN-skeleton motion at `fps` (`FrameRetargeter` over the clip); `target`: a
    `Rig`, a BN `Motion` or None (`default_rig()`); `source`: default matched by name."""
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
