"""Retargeting CMU-skeleton motions (CMU and Xia files) onto the Bandai Namco (BN) skeleton.

The BN skeleton has no T-pose: its bone offsets lie along each joint's local X and the pose with
all rotations zero is meaningless (legs point up the spine). So the mapping is built from bone
*directions*:

1. Both CMU naming variants (cgspeed: LeftUpLeg/LeftLeg/...; bvh11: LeftHip/LeftKnee/...) are
   mapped joint-for-joint onto BN joints by body position (`CMU_TO_BN`).
2. Hips and Chest have several children: their global rotation is a two-vector frame of the
   source joint positions (the bone up the spine and the left-right vector between the legs /
   shoulders), so the spine bone and the hip / shoulder line follow the source exactly.
3. Every other joint with a matched bone (`TwistPlan`, parents first): start from the BN parent's
   new global rotation times the joint's local rotation in the natural BN pose (`Rig.pose`), then
   apply the smallest swing that carries the BN bone onto the source bone direction. The bone
   points exactly where the source bone points, and the twist about it follows the BN parent and
   the natural pose, never the CMU joint's own twist (which puts e.g. knees 30 standard deviations
   outside BN's range for the LTI model). Limb roots (UpperLeg, UpperArm) instead take the twist
   that lays BN's hinge axis (the natural knee / elbow bend axis) along the normal of the source
   limb plane (hip-knee-ankle, shoulder-elbow-wrist), so knees and elbows bend about BN's hinge
   axis; a near-straight limb blends to the natural twist (`HINGE_FALLBACK`). Leaves (Head, Hands,
   Toes) keep the natural local rotation: they move no joint, and BN data holds them nearly fixed.
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


def _drivers(source: Skeleton, smap: dict[str, str]) -> dict[str, int]:
    """For each BN joint, the source joint whose global rotation moves the same body segment:
    the source parent of the mapped primary child (CMU puts zero-length joints in between, e.g.
    LowerBack, LHipJoint), or the mapped joint itself for leaves."""
    out = {}
    for name, src in smap.items():
        child = _PRIMARY_CHILD.get(name)
        out[name] = int(source.parents[source.index(smap[child])]) if child else source.index(src)
    return out


# BN limb joint -> its hinge child: the limb joint's twist is set by the plane of the limb
# (hip-knee-ankle, shoulder-elbow-wrist), so the hinge bends about the BN hinge axis.
_HINGES = {"UpperLeg_L": "LowerLeg_L", "UpperLeg_R": "LowerLeg_R", "UpperArm_L": "LowerArm_L", "UpperArm_R": "LowerArm_R"}
# How much a near-straight limb falls back to the natural twist: the hinge axis aims along
# cross(upper bone, lower bone) + HINGE_FALLBACK * (axis under the natural twist). |cross| is the
# sine of the bend, so the limb plane decides once the bend is well above ~6 degrees, and a straight
# (or slightly hyperextended) limb keeps the natural twist instead of flipping.
HINGE_FALLBACK = 0.03


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _swing_mats(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations (..., 3, 3) taking unit vectors a to unit vectors b (Rodrigues without
    trigonometry: I + [v]x + [v]x^2 / (1 + c), v = a x b, c = a . b). Exactly opposite vectors
    (a bone pointing exactly away from its natural direction in its parent's frame; not met in
    walks) get the half turn about an axis perpendicular to a."""
    v, c = np.cross(a, b), np.sum(a * b, axis=-1)
    flip = c < -1.0 + 1e-9
    if np.any(flip):  # replace v by a unit axis perpendicular to a; the formula then gives the half turn
        perp = np.cross(a, np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
        v = np.where(flip[..., None], _unit(perp), v)
        c = np.where(flip, -1.0 + 1e-12, c)
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    scale = np.where(flip, 1.0, 1.0 / (1.0 + c))[..., None, None]
    m = np.eye(3) + np.where(flip[..., None, None], 0.0, k) + (k @ k) * scale
    return m


def _lateral_frames(rig: Rig, source: Skeleton, s_pos: np.ndarray) -> np.ndarray:
    """World rotations (F, 2, 3, 3) of the two-vector joints (Hips, Chest) from source world positions (F, Js, 3)."""
    sk, smap = rig.skeleton, CMU_TO_BN[source_variant(source)]
    out = np.zeros((s_pos.shape[0], len(_LATERAL), 3, 3))
    for i, (name, (tl, tr)) in enumerate(_LATERAL.items()):
        child = _PRIMARY_CHILD[name]
        sl, sr = _SOURCE_LATERAL[name]
        up = s_pos[:, source.index(smap[child])] - s_pos[:, source.index(smap[name])]
        side = s_pos[:, source.index(smap[sl])] - s_pos[:, source.index(smap[sr])]
        m_tgt = _frame(sk.offsets[sk.index(child)], sk.offsets[sk.index(tl)] - sk.offsets[sk.index(tr)])
        out[:, i] = _frame(up, side) @ m_tgt.T
    return out


class TwistPlan:
    """The per-frame BN global rotations of one (rig, source skeleton) pair, batched over frames.

    Built once per source skeleton; `bn_globals` maps source world rotations to BN world rotations.
    Joints are processed depth by depth (parents first); within a depth, joints of one kind share
    each numpy call. Kinds:

    * lateral (Hips, Chest): two-vector frames, computed by the caller and passed in;
    * swing: BN parent's world rotation times the natural local rotation, then the smallest swing
      that carries the bone onto the source bone direction (twist about the bone follows the parent);
    * limb (UpperLeg, UpperArm): bone onto the source bone, twist such that the BN hinge axis (in
      the limb joint's frame, from the natural pose's bend) is the normal of the source limb plane;
    * leaf (Head, Hand, Toes): the natural local rotation under the new BN parent.

    `slots` maps source joint indices to rows of the `gs` passed to `bn_globals` (the streaming
    retargeter keeps only the joints it needs); `used` lists the source joints read.
    """

    def __init__(self, rig: Rig, source: Skeleton, slots: np.ndarray | None = None):
        sk = rig.skeleton
        smap = CMU_TO_BN[source_variant(source)]
        drivers = _drivers(source, smap)
        slot = (lambda k: int(k)) if slots is None else (lambda k: int(slots[k]))  # noqa: E731
        self.used = np.array(sorted(set(drivers.values())))
        self.num_joints = sk.num_joints
        self.lateral = np.array([sk.index(n) for n in _LATERAL])
        nat = Rotation.from_quat(rig.pose).as_matrix()  # (J, 3, 3) natural local rotations

        def off(n: str) -> np.ndarray:
            return sk.offsets[sk.index(n)]

        def src_dir(n: str) -> tuple[int, np.ndarray]:  # source bone into mapped child of BN joint n
            c = source.index(smap[_PRIMARY_CHILD[n]])
            return slot(drivers[n]), _unit(source.offsets[c])

        depth = np.zeros(sk.num_joints, int)
        for j, p in enumerate(sk.parents):
            depth[j] = depth[p] + 1 if p >= 0 else 0
        self.groups: list[tuple] = []
        for d in range(1, int(depth.max()) + 1):
            level = [sk.names[j] for j in range(sk.num_joints) if depth[j] == d and sk.names[j] not in _LATERAL]
            for kind in ("swing", "limb", "leaf"):
                names = [n for n in level if kind == ("limb" if n in _HINGES else "swing" if n in _PRIMARY_CHILD else "leaf")]
                if not names:
                    continue
                js = np.array([sk.index(n) for n in names])
                par = sk.parents[js]
                g = {"kind": kind, "j": js, "p": par, "nat": nat[js]}
                if kind in ("swing", "limb"):
                    g["b"] = np.stack([_unit(off(_PRIMARY_CHILD[n])) for n in names])
                    g["drv"], g["s"] = (np.array(x) for x in zip(*(src_dir(n) for n in names)))
                if kind == "limb":
                    hinge = [_HINGES[n] for n in names]
                    g["drv_c"], g["s_c"] = (np.array(x) for x in zip(*(src_dir(h) for h in hinge)))
                    # the natural bend's axis in the limb joint's frame: cross(upper bone, lower bone)
                    k = np.stack([_unit(np.cross(off(h), nat[sk.index(h)] @ off(_PRIMARY_CHILD[h]))) for h in hinge])
                    g["k"] = k
                    g["m_loc_t"] = np.swapaxes(_frame(g["b"], k), -1, -2)
                self.groups.append(g)

    def bn_globals(self, gs: np.ndarray, lateral: np.ndarray) -> np.ndarray:
        """BN world rotation matrices (B, J, 3, 3) from source world rotation matrices gs
        (B, rows, 3, 3) and the two-vector joints' world rotations `lateral` (B, 2, 3, 3)."""
        b = gs.shape[0]
        gb = np.empty((b, self.num_joints, 3, 3))
        gb[:] = np.eye(3)  # joint_Root
        gb[:, self.lateral] = lateral
        for g in self.groups:
            gp = gb[:, g["p"]]
            if g["kind"] == "leaf":
                gb[:, g["j"]] = gp @ g["nat"]
                continue
            base = gp @ g["nat"]  # natural local rotation under the BN parent
            d = (gs[:, g["drv"]] @ g["s"][..., None])[..., 0]  # source bone direction (world)
            rot = _swing_mats((base @ g["b"][..., None])[..., 0], d) @ base
            if g["kind"] == "limb":
                lower = (gs[:, g["drv_c"]] @ g["s_c"][..., None])[..., 0]
                natural = (rot @ g["k"][..., None])[..., 0]
                normal = np.cross(d, _unit(lower))
                w = np.sum(normal * natural, axis=-1, keepdims=True)
                axis = w * normal + HINGE_FALLBACK**2 * natural
                rot = _frame(d, axis) @ g["m_loc_t"]
            gb[:, g["j"]] = rot
        return gb


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

    n = src.num_frames
    s_rot, s_pos = src.global_transforms()
    gs = Rotation.from_quat(s_rot.reshape(-1, 4)).as_matrix().reshape(n, source.num_joints, 3, 3)
    lateral = _lateral_frames(rig, source, s_pos)
    gm = TwistPlan(rig, source).bn_globals(gs, lateral)
    lm = gm.copy()
    par = np.asarray(sk.parents)
    lm[:, par >= 0] = np.swapaxes(gm[:, par[par >= 0]], -1, -2) @ gm[:, par >= 0]
    local = Rotation.from_matrix(lm.reshape(-1, 3, 3)).as_quat().reshape(n, sk.num_joints, 4) if n else np.zeros((0, sk.num_joints, 4))
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
