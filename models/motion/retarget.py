"""Retargeting CMU-skeleton motions (CMU and Xia files) onto the Bandai Namco (BN) skeleton.

The BN skeleton has no T-pose: its bone offsets lie along each joint's local X and the pose with
all rotations zero is meaningless (legs point up the spine). So the mapping is built from bone
*directions*:

1. Both CMU naming variants (cgspeed: LeftUpLeg/LeftLeg/...; bvh11: LeftHip/LeftKnee/...) are
   mapped joint-for-joint onto BN joints by body position (`CMU_TO_BN`).
2. Reference ("alignment") rotations `Q_j`: the BN global rotations that put BN into the CMU rest
   pose (every CMU rotation zero). For a joint with one child, `Q_j` is the smallest rotation that
   swings the bone of a natural BN pose (a frame of BN data, turned to face the same way as the CMU
   rest pose) onto the CMU rest bone direction; the natural pose fixes the twist about the bone.
   Hips and Chest have several children: their global rotation is fixed by two vectors (the bone
   up the spine and the left-right vector between the legs / shoulders).
3. Per frame, BN global rotation = CMU global rotation of the joint that drives the same body
   segment x `Q_j` (for Hips and Chest: the two-vector frame of the CMU joint positions of that
   frame, so the spine bone and the hip / shoulder line follow CMU exactly), then back to
   local rotations. Each mapped BN bone then points exactly where the CMU bone points.
4. Hips translation is scaled by the leg-length ratio (BN thigh + shin / CMU thigh + shin, which
   also converts CMU units to cm) and shifted vertically so that the toe on the ground sits at the
   toe height the BN data shows (~4.2 cm; see `contact_height`). The source is first resampled to
   the target fps (default 30).

Everything is pure numpy/scipy; `default_rig()` comes from a committed one-frame BN asset.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from .resample import resample
from .rotations import quat_canonical
from .skeleton import Motion, Skeleton, fk

# BN joint -> CMU joint at the same body position, for the two CMU naming variants.
_CGSPEED = {
    "Hips": "Hips", "Spine": "Spine", "Chest": "Spine1", "Neck": "Neck1", "Head": "Head",
    "Shoulder_L": "LeftShoulder", "UpperArm_L": "LeftArm", "LowerArm_L": "LeftForeArm", "Hand_L": "LeftHand",
    "Shoulder_R": "RightShoulder", "UpperArm_R": "RightArm", "LowerArm_R": "RightForeArm", "Hand_R": "RightHand",
    "UpperLeg_L": "LeftUpLeg", "LowerLeg_L": "LeftLeg", "Foot_L": "LeftFoot", "Toes_L": "LeftToeBase",
    "UpperLeg_R": "RightUpLeg", "LowerLeg_R": "RightLeg", "Foot_R": "RightFoot", "Toes_R": "RightToeBase",
}
_BVH11 = {
    "Hips": "Hips", "Spine": "Chest", "Chest": "Chest2", "Neck": "Neck", "Head": "Head",
    "Shoulder_L": "LeftCollar", "UpperArm_L": "LeftShoulder", "LowerArm_L": "LeftElbow", "Hand_L": "LeftWrist",
    "Shoulder_R": "RightCollar", "UpperArm_R": "RightShoulder", "LowerArm_R": "RightElbow", "Hand_R": "RightWrist",
    "UpperLeg_L": "LeftHip", "LowerLeg_L": "LeftKnee", "Foot_L": "LeftAnkle", "Toes_L": "LeftToe",
    "UpperLeg_R": "RightHip", "LowerLeg_R": "RightKnee", "Foot_R": "RightAnkle", "Toes_R": "RightToe",
}
CMU_TO_BN = {"cgspeed": _CGSPEED, "bvh11": _BVH11}

BN_JOINTS = ("joint_Root", "Hips", "Spine", "Chest", "Neck", "Head",
             "Shoulder_L", "UpperArm_L", "LowerArm_L", "Hand_L", "Shoulder_R", "UpperArm_R", "LowerArm_R", "Hand_R",
             "UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L", "UpperLeg_R", "LowerLeg_R", "Foot_R", "Toes_R")

# BN joint -> the child whose bone its rotation is matched on (joints not listed are leaves).
_PRIMARY_CHILD = {
    "Hips": "Spine", "Spine": "Chest", "Chest": "Neck", "Neck": "Head",
    "Shoulder_L": "UpperArm_L", "UpperArm_L": "LowerArm_L", "LowerArm_L": "Hand_L",
    "Shoulder_R": "UpperArm_R", "UpperArm_R": "LowerArm_R", "LowerArm_R": "Hand_R",
    "UpperLeg_L": "LowerLeg_L", "LowerLeg_L": "Foot_L", "Foot_L": "Toes_L",
    "UpperLeg_R": "LowerLeg_R", "LowerLeg_R": "Foot_R", "Foot_R": "Toes_R",
}
# Joints with several children: (left child, right child) fixing the twist of the up vector.
# Source side uses the mapped joints of `_SOURCE_LATERAL` (CMU collars sit on the spine, so the
# chest's left-right vector is taken between the shoulder joints).
_LATERAL = {"Hips": ("UpperLeg_L", "UpperLeg_R"), "Chest": ("Shoulder_L", "Shoulder_R")}
_SOURCE_LATERAL = {"Hips": ("UpperLeg_L", "UpperLeg_R"), "Chest": ("UpperArm_L", "UpperArm_R")}

# Bones (BN parent, BN child) that span the same body segment in both skeletons: their directions
# are matched exactly and are what `bone_directions` compares.
MATCHED_BONES = tuple((p, c) for p, c in _PRIMARY_CHILD.items())


@dataclass(frozen=True)
class Rig:
    """A retargeting target: the skeleton, a natural pose that fixes limb twist, and floor height."""

    skeleton: Skeleton
    pose: np.ndarray  # (J, 4) local rotations of a natural (standing or walking) pose
    floor: float  # toe height on the ground in the target's data (`contact_height`, target units)
    euler_orders: tuple[str, ...] = ()  # per joint, for writing BVH like the target's files

    @classmethod
    def from_motion(cls, motion: Motion, frame: int = 0) -> Rig:
        sk = motion.skeleton
        missing = [n for n in BN_JOINTS if n not in sk.names]
        if missing:
            raise ValueError(f"not a Bandai Namco skeleton (missing {', '.join(missing)})")
        toes = [sk.index("Toes_L"), sk.index("Toes_R")]
        floor = contact_height(motion.global_positions()[:, toes, 1])
        return cls(sk, np.array(motion.rotations[frame], dtype=float), floor, tuple(motion.euler_orders))


def contact_height(toe_heights: np.ndarray, percentile: float = 5.0) -> float:
    """Toe height when on the ground: a low percentile of the lowest toe per frame (F, 2). Robust
    to single-frame dips in the data, and still the contact height for runs and jumps."""
    return float(np.percentile(np.asarray(toe_heights).min(axis=-1), percentile))


def source_variant(skeleton: Skeleton) -> str:
    """'cgspeed' or 'bvh11', the CMU naming variant of a skeleton."""
    for variant, mapping in CMU_TO_BN.items():
        if all(name in skeleton.names for name in mapping.values()):
            return variant
    raise ValueError(f"not a CMU skeleton I know: {', '.join(skeleton.names)}")


@lru_cache(maxsize=1)
def default_rig() -> Rig:
    """The BN rig from the committed asset (first frame of Bandai Namco data set 2's first normal
    walk, and that clip's toe floor), so retargeting needs no data at serving time."""
    from .assets import BANDAI_NAMCO_TOE_FLOOR, bandai_namco_pose

    pose = bandai_namco_pose()
    return Rig(pose.skeleton, np.array(pose.rotations[0], dtype=float), BANDAI_NAMCO_TOE_FLOOR, tuple(pose.euler_orders))


def leg_length(skeleton: Skeleton, variant: str | None = None) -> float:
    """Thigh + shin length (mean of both legs) of a BN or CMU skeleton, in its own units."""
    names = dict(zip(BN_JOINTS, BN_JOINTS)) if variant is None else CMU_TO_BN[variant]
    return 0.5 * sum(skeleton.chain_length(names[f"UpperLeg_{s}"], names[f"Foot_{s}"]) for s in "LR")


def _frame(primary: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """Orthonormal frames (..., 3, 3) with columns (primary, lateral made orthogonal, their cross)."""
    e1 = primary / np.linalg.norm(primary, axis=-1, keepdims=True)
    e2 = lateral - np.sum(lateral * e1, axis=-1, keepdims=True) * e1
    e2 = e2 / np.linalg.norm(e2, axis=-1, keepdims=True)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=-1)


def _swing(a: np.ndarray, b: np.ndarray) -> Rotation:
    """Smallest rotation taking direction a to direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-9:
        if c > 0:
            return Rotation.identity()
        perp = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        return Rotation.from_rotvec(np.pi * perp / np.linalg.norm(perp))
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c))


def _yaw_between(a: np.ndarray, b: np.ndarray) -> Rotation:
    """Rotation about +Y taking the horizontal part of a onto that of b."""
    ang = np.arctan2(a[0], a[2]) - np.arctan2(b[0], b[2])  # heading angle about Y: atan2(x, z)
    return Rotation.from_rotvec([0.0, -ang, 0.0])


def alignment(rig: Rig, source: Skeleton) -> dict[str, np.ndarray]:
    """BN global rotations (quaternions) that put the BN skeleton into the source's rest pose."""
    sk, smap = rig.skeleton, CMU_TO_BN[source_variant(source)]
    src_rest = source.rest_positions()

    def src_vec(a: str, b: str) -> np.ndarray:  # source rest vector between the joints mapped from BN a, b
        return src_rest[source.index(smap[b])] - src_rest[source.index(smap[a])]

    def off(name: str) -> np.ndarray:
        return sk.offsets[sk.index(name)]

    # The natural BN pose, turned about Y so its left-right axis matches the source rest pose's.
    g_nat, _ = fk(rig.pose, sk.offsets, sk.parents)
    nat = {n: Rotation.from_quat(g_nat[sk.index(n)]) for n in sk.names}
    bn_left = nat["Hips"].apply(off("UpperLeg_L") - off("UpperLeg_R"))
    yaw = _yaw_between(bn_left, src_vec("UpperLeg_R", "UpperLeg_L"))
    nat = {n: yaw * r for n, r in nat.items()}

    q: dict[str, Rotation] = {"joint_Root": Rotation.identity()}
    for j, name in enumerate(sk.names):
        if name == "joint_Root":
            continue
        if name in _LATERAL:
            child = _PRIMARY_CHILD[name]
            (tl, tr), (sl, sr) = _LATERAL[name], _SOURCE_LATERAL[name]
            m_src = _frame(src_vec(name, child), src_vec(sr, sl))
            m_tgt = _frame(off(child), off(tl) - off(tr))
            q[name] = Rotation.from_matrix(m_src @ m_tgt.T)
        elif name in _PRIMARY_CHILD:
            child = _PRIMARY_CHILD[name]
            q[name] = _swing(nat[name].apply(off(child)), src_vec(name, child)) * nat[name]
        else:  # leaf: keep the natural pose's rotation relative to the parent
            parent = sk.names[sk.parents[j]]
            q[name] = q[parent] * nat[parent].inv() * nat[name]
    return {n: r.as_quat() for n, r in q.items()}


def _drivers(source: Skeleton, smap: dict[str, str]) -> dict[str, int]:
    """For each BN joint, the source joint whose global rotation moves the same body segment:
    the source parent of the mapped primary child (CMU puts zero-length joints in between, e.g.
    LowerBack, LHipJoint), or the mapped joint itself for leaves."""
    out = {}
    for name, src in smap.items():
        child = _PRIMARY_CHILD.get(name)
        out[name] = int(source.parents[source.index(smap[child])]) if child else source.index(src)
    return out


def retarget(motion: Motion, target: Rig | Motion | None = None, fps: float = 30.0) -> Motion:
    """A CMU-skeleton motion (either naming variant) as a BN-skeleton motion at `fps`.

    `target` is a `Rig`, a BN `Motion` (its first frame and toe heights make the rig) or None for
    `default_rig()`. The result has the target's joints in the target's order; every translation is
    the target offset except Hips, which carries the scaled root motion.
    """
    rig = default_rig() if target is None else target if isinstance(target, Rig) else Rig.from_motion(target)
    src = resample(motion, fps)
    source, sk = src.skeleton, rig.skeleton
    variant = source_variant(source)
    smap = CMU_TO_BN[variant]
    q = alignment(rig, source)
    drivers = _drivers(source, smap)

    n = src.num_frames
    s_rot, s_pos = src.global_transforms()
    s_R = [Rotation.from_quat(s_rot[:, j]) for j in range(source.num_joints)]

    g = np.zeros((n, sk.num_joints, 4))
    for j, name in enumerate(sk.names):
        if name == "joint_Root":
            g[:, j] = [0.0, 0.0, 0.0, 1.0]
        elif name in _LATERAL:
            child = _PRIMARY_CHILD[name]
            sl, sr = _SOURCE_LATERAL[name]
            up = s_pos[:, source.index(smap[child])] - s_pos[:, source.index(smap[name])]
            side = s_pos[:, source.index(smap[sl])] - s_pos[:, source.index(smap[sr])]
            tl, tr = _LATERAL[name]
            m_tgt = _frame(sk.offsets[sk.index(child)], sk.offsets[sk.index(tl)] - sk.offsets[sk.index(tr)])
            g[:, j] = Rotation.from_matrix(_frame(up, side) @ m_tgt.T).as_quat()
        else:
            g[:, j] = (s_R[drivers[name]] * Rotation.from_quat(q[name])).as_quat()

    local = np.zeros_like(g)
    for j, p in enumerate(sk.parents):
        if p < 0:
            local[:, j] = g[:, j]
        else:
            local[:, j] = (Rotation.from_quat(g[:, p]).inv() * Rotation.from_quat(g[:, j])).as_quat()
    local = quat_canonical(local)

    scale = leg_length(sk) / leg_length(source, variant)
    trans = np.broadcast_to(sk.offsets, (n, sk.num_joints, 3)).copy()
    hips = sk.index("Hips")
    trans[:, hips] = s_pos[:, source.index(smap["Hips"])] * scale
    if n:
        _, pos = fk(local, trans, sk.parents)
        toes = [sk.index("Toes_L"), sk.index("Toes_R")]
        trans[:, hips, 1] += rig.floor - contact_height(pos[:, toes, 1])
    return Motion(sk, local, trans, float(fps), rig.euler_orders or tuple("ZXY" for _ in sk.names))


def bone_directions(motion: Motion, bones: list[tuple[str, str]], names: dict[str, str] | None = None) -> np.ndarray:
    """Unit world directions (F, B, 3) of bones given as (joint, child) pairs of BN names,
    translated to the motion's own joints through `names` (e.g. `CMU_TO_BN[variant]`)."""
    sk = motion.skeleton
    pos = motion.global_positions()
    idx = [(sk.index(names[a] if names else a), sk.index(names[b] if names else b)) for a, b in bones]
    vec = np.stack([pos[:, b] - pos[:, a] for a, b in idx], axis=1)
    return vec / np.linalg.norm(vec, axis=-1, keepdims=True).clip(min=1e-9)
