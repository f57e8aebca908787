"""Causal per-frame motion features, usable on a live stream: every feature at frame t depends
only on frames <= t (backward differences; facing from the current pose alone).

Conventions: Y up; the facing frame sits at the Hips on the ground with +Z along forward =
left x up, "left" from the right hip/shoulder to the left one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .humanoid import CMU_TO_BN
from .rotations import matrix_to_quat, quat_to_matrix, wrap_angle
from .skeleton import Motion, Skeleton

UP = np.array([0.0, 1.0, 0.0])

# Candidate joint names per body part, first match wins: BN's, then CMU's two namings (cgspeed,
# then bvh11: order matters, "LeftShoulder" is the upper arm in one and the collar in the other).
_PART_BN = {
    "hips": "Hips",
    "hip_l": "UpperLeg_L",
    "hip_r": "UpperLeg_R",
    "shoulder_l": "UpperArm_L",
    "shoulder_r": "UpperArm_R",
    "ankle_l": "Foot_L",
    "ankle_r": "Foot_R",
    "toe_l": "Toes_L",
    "toe_r": "Toes_R",
}
_PARTS = {
    part: tuple(dict.fromkeys((bn, *(names[bn] for names in CMU_TO_BN.values())))) for part, bn in _PART_BN.items()
}


def body_joint(skeleton: Skeleton, part: str) -> int:
    for name in _PARTS[part]:
        if name in skeleton.names:
            return skeleton.names.index(name)
    raise KeyError(f"skeleton has no joint for {part!r} (tried {', '.join(_PARTS[part])})")


def left_leg_length(skeleton: Skeleton) -> float:
    """Left hip-to-ankle rest length: the scale of thresholds and features (between rigs: `humanoid.leg_length`)."""
    rest = skeleton.rest_positions()
    hip, knee_to_ankle = body_joint(skeleton, "hip_l"), body_joint(skeleton, "ankle_l")
    total, j = 0.0, knee_to_ankle
    while j != hip:
        total += float(np.linalg.norm(rest[j] - rest[skeleton.parents[j]]))
        j = int(skeleton.parents[j])
    return total


def facing_yaw(positions: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """Yaw (radians about +Y, 0 = facing +Z) of each pose from world positions (..., J, 3)."""
    left = (
        positions[..., body_joint(skeleton, "hip_l"), :]
        - positions[..., body_joint(skeleton, "hip_r"), :]
        + positions[..., body_joint(skeleton, "shoulder_l"), :]
        - positions[..., body_joint(skeleton, "shoulder_r"), :]
    )
    forward = np.cross(left, UP)
    return np.arctan2(forward[..., 0], forward[..., 2])


def yaw_matrix(yaw: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations about +Y by `yaw`."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros(np.shape(yaw) + (3, 3))
    out[..., 0, 0], out[..., 0, 2], out[..., 1, 1], out[..., 2, 0], out[..., 2, 2] = c, s, 1.0, -s, c
    return out


def backward_diff(x: np.ndarray, fps: float) -> np.ndarray:
    """d/dt along axis 0 from the current and previous frame only; zero at frame 0."""
    out = np.zeros_like(x)
    out[1:] = (x[1:] - x[:-1]) * fps
    return out


@dataclass
class Features:
    yaw: np.ndarray  # (F,) facing yaw, radians
    local_positions: np.ndarray  # (F, J, 3) joint positions in the facing frame
    root_velocity: np.ndarray  # (F, 3) root velocity in the facing frame (units/s), y = vertical
    yaw_rate: np.ndarray  # (F,) radians/s
    joint_velocities: np.ndarray  # (F, J, 3) world joint velocities expressed in the facing frame
    contacts: np.ndarray  # (F, 2) bool, left and right foot


def foot_contacts(
    positions: np.ndarray, skeleton: Skeleton, fps: float, height: float = 0.12, speed: float = 0.5
) -> np.ndarray:
    """(F, 2) contacts: ankle or toe within `height` leg lengths of y = 0, slower than `speed` per second."""
    leg = left_leg_length(skeleton)
    out = []
    for side in ("l", "r"):
        planted = np.zeros(positions.shape[0], dtype=bool)
        for part, h in ((f"ankle_{side}", height * 1.8), (f"toe_{side}", height)):
            p = positions[:, body_joint(skeleton, part)]
            v = np.linalg.norm(backward_diff(p, fps), axis=-1)
            planted |= (p[:, 1] < h * leg) & (v < speed * leg)
        out.append(planted)
    return np.stack(out, axis=-1)


def compute_features(motion: Motion) -> Features:
    _, pos = motion.global_transforms()
    sk = motion.skeleton
    yaw = facing_yaw(pos, sk)
    to_local = np.swapaxes(yaw_matrix(yaw), -1, -2)  # inverse yaw
    root = pos[:, body_joint(sk, "hips")] * np.array([1.0, 0.0, 1.0])
    local = np.einsum("fab,fjb->fja", to_local, pos - root[:, None])
    world_root_vel = backward_diff(pos[:, body_joint(sk, "hips")], motion.fps)
    yaw_rate = np.zeros_like(yaw)
    yaw_rate[1:] = wrap_angle(np.diff(yaw)) * motion.fps
    return Features(
        yaw=yaw,
        local_positions=local,
        root_velocity=np.einsum("fab,fb->fa", to_local, world_root_vel),
        yaw_rate=yaw_rate,
        joint_velocities=np.einsum("fab,fjb->fja", to_local, backward_diff(pos, motion.fps)),
        contacts=foot_contacts(pos, sk, motion.fps),
    )


# --------------------------------------------------------------------------- mirroring

_REFLECTIONS = [np.array(d, dtype=float) for d in ((-1, -1, -1), (-1, 1, 1), (1, -1, 1), (1, 1, -1))]
WORLD_MIRROR = np.array([-1.0, 1.0, 1.0])  # reflect the world's X axis


def mirror_reflections(skeleton: Skeleton) -> np.ndarray:
    """Per joint, the sign vector S_j with offset[mirror(c)] = S_j * offset[c] (CMU: -x, BN: -I on limbs)."""
    mirror = skeleton.mirror_map()
    scale = float(np.abs(skeleton.offsets).max())
    out = np.zeros((skeleton.num_joints, 3))
    for j in range(skeleton.num_joints):
        parent = skeleton.parents[j]
        candidates = [out[parent] if parent >= 0 else WORLD_MIRROR, *_REFLECTIONS]
        pairs = [(skeleton.offsets[c], skeleton.offsets[mirror[c]]) for c in skeleton.children(j)]
        if not np.isnan(skeleton.end_sites[j]).any():
            pairs.append((skeleton.end_sites[j], skeleton.end_sites[mirror[j]]))
        if parent < 0:
            pairs = []  # the root's children may move per frame (BN Hips); their translations are mirrored as data
        fits = [s for s in candidates if all(_same_direction(s * a, b, scale) for a, b in pairs)]
        if not fits:
            raise ValueError(f"skeleton is not left/right symmetric at joint {skeleton.names[j]!r}")
        out[j] = fits[0]
    return out


def _same_direction(a: np.ndarray, b: np.ndarray, scale: float) -> bool:
    """Bones match in direction (within ~10 degrees); lengths may differ side to side."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if max(na, nb) < 1e-3 * scale:
        return True
    return bool(na > 0 and nb > 0 and a @ b / (na * nb) > 0.985)


def mirror(motion: Motion) -> Motion:
    """Left/right mirror image (world X reflected): R'_j = S_parent R_mirror(j) S_j, t'_j = S_parent t_mirror(j)."""
    sk = motion.skeleton
    m = sk.mirror_map()
    s = mirror_reflections(sk)
    s_parent = np.stack([s[p] if p >= 0 else WORLD_MIRROR for p in sk.parents])
    mats = quat_to_matrix(motion.rotations[:, m])  # (F, J, 3, 3)
    mats = s_parent[None, :, :, None] * mats * s[None, :, None, :]
    translations = motion.translations[:, m] * s_parent[None]
    return replace(motion, rotations=matrix_to_quat(mats), translations=translations)
