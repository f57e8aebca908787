"""Retargeting humanoid motions (any rig `humanoid` matches: CMU and Xia files, Mixamo, Unreal,
Unity/VRM, SMPL, BVH exports, ...) onto the Bandai Namco (BN) skeleton.

The BN skeleton has no T-pose (its all-zero pose points the legs up the spine), so the mapping
is built from bone *directions*, never from either skeleton's rest pose:

1. `humanoid.match_roles` names the client joint of each body role; `humanoid.bn_segments`
   gives, per BN bone, the client segment (between two role joints) whose direction it takes.
2. Hips and Chest have several children: their global rotation is a two-vector frame of the
   client's joint positions (the bone up the spine and the line between the legs / upper arms).
   The hips' side vector is the client's rest hip line carried by its hips joint
   (`retarget_stream._rest_side`), so hip joints between hips and thighs do not turn the pelvis.
3. Every other joint with a segment (`TwistPlan`, parents first): the BN parent's new global
   rotation times the joint's local rotation in the natural BN pose, then the smallest swing that
   carries the BN bone onto the segment. The twist about the bone follows the BN parent and the
   natural pose, never the client joint's own twist (which can sit far outside BN's range).
   Limb roots (UpperLeg, UpperArm) instead take the twist that lays BN's hinge axis along the
   normal of the client's limb plane, cross(upper bone, lower bone), so knees and elbows bend
   about BN's hinge; a near-straight limb, whose plane is noise, blends to a fallback axis
   (`HINGE_FALLBACK`): halfway between BN's natural hinge axis and the client's own hinge axis,
   learned per stream from its bent frames (`HINGE_PRIOR`; `retarget_stream.FrameRetargeter`
   keeps it as the stream's state). The Spine takes a share of the Chest's twist (`TWIST_SHARE`), as Unity's
   humanoid spreads a twist over a chain. Leaves (Head, Hands, Toes) keep the natural local
   rotation: they move no joint, and BN data holds them nearly fixed.
4. The Hips translation is scaled by the leg-length ratio (which also converts units) and shifted
   so the toe on the ground sits at the toe height BN data shows (`contact_height`). The source
   is first resampled to the target fps (default 30).

Pure numpy/scipy; `default_rig()` comes from a committed one-frame BN asset.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from .bn_skeleton import PRIMARY_CHILD, missing_joints
from .humanoid import HumanoidRig
from .resample import resample
from .rotations import quat_canonical
from .skeleton import Motion, Skeleton, fk

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

    @classmethod
    def from_motion(cls, motion: Motion, frame: int = 0) -> Rig:
        sk = motion.skeleton
        missing = missing_joints(sk.names)
        if missing:
            raise ValueError(f"not a Bandai Namco skeleton (missing {', '.join(missing)})")
        toes = [sk.index("Toes_L"), sk.index("Toes_R")]
        floor = contact_height(motion.global_positions()[:, toes, 1])
        return cls(sk, np.array(motion.rotations[frame], dtype=float), floor, tuple(motion.euler_orders))


def contact_height(toe_heights: np.ndarray, percentile: float = 5.0) -> float:
    """Toe height when on the ground: a low percentile of the lowest toe per frame (F, 2). Robust
    to single-frame dips in the data, and still the contact height for runs and jumps."""
    return float(np.percentile(np.asarray(toe_heights).min(axis=-1), percentile))


@lru_cache(maxsize=1)
def default_rig() -> Rig:
    """The BN rig from the committed asset (first frame of Bandai Namco data set 2's first normal
    walk, and that clip's toe floor), so retargeting needs no data at serving time."""
    from .assets import BANDAI_NAMCO_TOE_FLOOR, bandai_namco_pose

    pose = bandai_namco_pose()
    return Rig(
        pose.skeleton, np.array(pose.rotations[0], dtype=float), BANDAI_NAMCO_TOE_FLOOR, tuple(pose.euler_orders)
    )


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
# How much a near-straight limb falls back to its fallback axis: the hinge axis aims along
# |n| n + HINGE_FALLBACK^2 fallback, n = cross(upper bone, lower bone), |n| the sine of the bend.
# The limb plane decides once the bend is well above ~35 degrees; a straighter limb turns smoothly
# to the fallback. An axis weighted by (n . fallback) instead flips whenever the plane crosses a
# quarter turn from the fallback (CMU's right arm) or a hyperextended knee straightens (Xia's
# thighs). The fallback is the unit mean of BN's natural hinge axis, which swings with the limb's
# direction, and the client's own hinge axis, fixed in the frame of the client joint that carries
# the hinge child and learned per stream: the natural axis at the stream's first frame
# (`HINGE_PRIOR`), plus each frame's limb-plane normal weighted by sin^2 of its bend (a
# near-straight limb's plane is noise). With the natural axis alone a straightening limb's twist
# turned within a few frames where the two disagree (the Xia punch's arms 1.7-1.9x the source's
# p99 rotation acceleration, Xia legs at 120 fps 1.35-1.6x; `retarget_check`); with the client's
# axis alone, BN's arm twist takes the client's upper arm twist (Xia jump's arms 1.3-1.8x). With
# the mean, worst 1.18 at 0.6 and 1.22 at 0.5. A stronger fallback holds moderately bent knees
# off their limb plane: the Xia walk's mean LTI blend weight rises from 0.80 (0.3, natural axis)
# to 0.92 (tests/test_retarget.py).
HINGE_FALLBACK = 0.6
# The weight of the stream's first natural axis in its learned hinge axis, against sin^2 of the bend
# per frame: a stream that never bends a limb (the Xia punch's legs) keeps that axis turning with
# its client joint, so BN's twist follows the client's; one that does soon outweighs it.
HINGE_PRIOR = 1.0


# The share of the chest's twist about the spine bone (relative to the natural pose) that BN's Spine
# takes, as Unity's humanoid spreads a twist over the joints of a chain: with none, a client's
# whole spine twist lands in BN's Chest, whose rotation then jitters 1.8x the client's worst spine
# joint (Xia runs; retarget_check).
TWIST_SHARE = 0.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class TwistPlan:
    """BN global rotations from client bone directions, batched over frames.

    `segments` lists the BN joints (other than the two-vector joints Hips and Chest) whose bone
    direction the caller gives, in the order of the columns of `dirs`; BN joints not listed are
    leaves. Joints are processed depth by depth (parents first); within a depth, joints of one
    kind share each numpy call. Kinds:

    * lateral (Hips, Chest): two-vector frames, computed by the caller and passed in;
    * swing: BN parent's world rotation times the natural local rotation, then the smallest swing
      that carries the bone onto the given direction (twist about the bone follows the parent);
    * limb (UpperLeg, UpperArm): bone onto the given direction, twist such that the BN hinge axis
      (in the limb joint's frame, from the natural pose's bend) is the normal of the client's limb
      plane (upper and lower bone directions), or the fallback axis (`HINGE_FALLBACK`) when the
      limb is near straight;
    * leaf (Head, Hand, Toes, and Foot when the client has no toes): the natural local rotation
      under the new BN parent.
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
            return "limb" if n in _HINGES and _HINGES[n] in col else "swing"

        depth = np.zeros(sk.num_joints, int)
        for j, p in enumerate(sk.parents):
            depth[j] = depth[p] + 1 if p >= 0 else 0
        self.groups: list[dict] = []
        for d in range(1, int(depth.max()) + 1):
            level = [sk.names[j] for j in range(sk.num_joints) if depth[j] == d and sk.names[j] not in _LATERAL]
            for kind in ("swing", "limb", "leaf"):
                names = [n for n in level if kind_of(n) == kind]
                if not names:
                    continue
                js = np.array([sk.index(n) for n in names])
                g = {"kind": kind, "j": js, "p": sk.parents[js], "nat": nat[js]}
                if kind in ("swing", "limb"):
                    g["b"] = np.stack([_unit(off(PRIMARY_CHILD[n])) for n in names])
                    g["dir"] = np.array([col[n] for n in names])
                if kind == "swing" and any(PRIMARY_CHILD[n] in _LATERAL for n in names):
                    (n,) = names  # the spine: one joint under Hips, the Chest above it
                    c = sk.index(PRIMARY_CHILD[n])
                    g["split"] = (c, nat[c])
                if kind == "limb":
                    hinge = [_HINGES[n] for n in names]
                    g["dir_c"] = np.array([col[h] for h in hinge])
                    g["h"] = np.array([list(_HINGES).index(n) for n in names])  # the hinge's row in a stream's state
                    # the natural bend's axis in the limb joint's frame: cross(upper bone, lower bone)
                    k = np.stack([_unit(np.cross(off(h), nat[sk.index(h)] @ off(PRIMARY_CHILD[h]))) for h in hinge])
                    g["k"] = k
                    g["m_loc_t"] = np.swapaxes(_frame(g["b"], k), -1, -2)
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
    src = resample(motion, fps)
    fr = FrameRetargeter(source if source is not None else motion.skeleton, rig)
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
