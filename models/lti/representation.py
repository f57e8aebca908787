"""Hsu et al. 2005 motion representation of whole clips (the compiled step streams it, `kernels.py`).

Per frame of the Bandai Namco skeleton (22 joints, `joint_Root` static at 0, `Hips` at 1):

  [0:2]   root ground-plane displacement (x, z) since the previous frame, expressed in the
          previous frame's facing frame (+Z forward, +X left)
  [2]     yaw change since the previous frame (radians, wrapped to [-pi, pi))
  [3]     root height (Hips y, cm)
  [4:7]   the Hips rotation with its yaw removed ("tilt"), exponential map
  [7:67]  local rotations of joints 2..21 (Spine ... Toes_R), exponential map

Rotations are relative to a per-joint reference `ref` (22, 4), q = ref_j * exp(r), since several BN
joints sit near 180 degrees where exp wraps. Yaw 0 faces +Z; the split q_hips = q_yaw * q_tilt is
exact, so the representation inverts exactly, and offline and streaming agree to round-off.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from models.motion.bn_skeleton import HIPS, NUM_JOINTS
from models.motion.rotations import quat_inv, rotate_y, wrap_angle

if TYPE_CHECKING:
    from models.motion.skeleton import Motion

ROOT_DIMS = 7
BODY_JOINTS = tuple(range(2, NUM_JOINTS))  # joints carried as expmaps
FEATURE_DIM = ROOT_DIMS + 3 * len(BODY_JOINTS)  # 67


# --------------------------------------------------------------------------- quaternions


def left_matrix(p: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 4, 4) L with quat_mul(p, q) == L @ q."""
    x, y, z, w = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    rows = [[w, -z, y, x], [z, w, -x, y], [-y, x, w, z], [-x, -y, -z, w]]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


IDENTITY_REF = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (NUM_JOINTS, 1))


def mean_rotations(rotations: np.ndarray) -> np.ndarray:
    """(F, 22, 4) -> (22, 4) per-joint mean rotation, the Hips' over the yaw-free tilt."""
    q = rotations.copy()
    q[:, HIPS] = split_hips(q[:, HIPS])[1]
    ref = np.empty((NUM_JOINTS, 4))
    for j in range(NUM_JOINTS):
        w, v = np.linalg.eigh(q[:, j].T @ q[:, j])
        ref[j] = v[:, -1] * (1.0 if v[3, -1] >= 0 else -1.0)
    return ref


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 3) exponential map, angle in [0, pi] (w >= 0 branch)."""
    w = np.abs(q[..., 3:])
    v = q[..., :3] * np.sign(q[..., 3:] + 1e-300)
    s = np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]
    # angle / sin(angle / 2) -> 2 / w as s -> 0
    scale = np.divide(2.0 * np.arctan2(s, w), s, out=2.0 / np.maximum(w, 1e-12), where=s > 1e-8)
    return v * scale


def hips_yaw(q_hips: np.ndarray) -> np.ndarray:
    # left = R(q) @ (0, -1, 0) = -(second matrix column); forward = cross(left, up) = (-left_z, 0, left_x)
    x, y, z, w = q_hips[..., 0], q_hips[..., 1], q_hips[..., 2], q_hips[..., 3]
    left_x = -2.0 * (x * y - w * z)
    left_z = -2.0 * (y * z + w * x)
    return np.arctan2(-left_z, left_x)  # yaw = atan2(fwd_x, fwd_z)


def split_hips(q_hips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q_hips = yaw_quat(yaw) * tilt; returns (yaw, tilt quaternion)."""
    yaw = hips_yaw(q_hips)
    c, s = np.cos(0.5 * yaw)[..., None], np.sin(0.5 * yaw)[..., None]
    # yaw_quat(-yaw) * q, written out: (c*x - s*z, c*y - s*w, c*z + s*x, c*w + s*y)
    return yaw, c * q_hips + s * q_hips[..., [2, 3, 0, 1]] * np.array([-1.0, -1.0, 1.0, 1.0])


# --------------------------------------------------------------------------- offline


def pose_features(
    root: np.ndarray, rotations: np.ndarray, ref: np.ndarray = IDENTITY_REF
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame pieces that need no history: (yaw (...), ground xz (..., 2), static features (..., 64))."""
    yaw, tilt = split_hips(rotations[..., HIPS, :])
    q = rotations[..., 1:, :].copy()
    q[..., 0, :] = tilt
    inv_ref = _left_inv(ref)
    r = quat_to_rotvec((inv_ref @ q[..., None])[..., 0]).reshape(*rotations.shape[:-2], 3 * (NUM_JOINTS - 1))
    static = np.concatenate([root[..., 1:2], r], axis=-1)
    return yaw, root[..., [0, 2]], static


def sequence_features(root: np.ndarray, rotations: np.ndarray, ref: np.ndarray = IDENTITY_REF) -> np.ndarray:
    """(F, 3) Hips translations + (F, J, 4) local rotations -> (F, 67) features."""
    yaw, ground, static = pose_features(root, rotations, ref)
    delta = np.zeros((len(yaw), 3))
    if len(yaw) > 1:
        delta[1:, :2] = rotate_y(ground[1:] - ground[:-1], -yaw[:-1])
        delta[1:, 2] = wrap_angle(yaw[1:] - yaw[:-1])
    return np.concatenate([delta, static], axis=-1)


def motion_to_features(motion: Motion, ref: np.ndarray = IDENTITY_REF) -> np.ndarray:
    return sequence_features(motion.translations[:, HIPS], motion.rotations, ref)


_LEFT_CACHE: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _cached(ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    key = id(ref)
    hit = _LEFT_CACHE.get(key)
    if hit is None or hit[0] is not ref:
        hit = (ref, left_matrix(ref[1:]), left_matrix(quat_inv(ref[1:])))
        _LEFT_CACHE[key] = hit
    return hit[1], hit[2]


def _left_inv(ref: np.ndarray) -> np.ndarray:
    return _cached(ref)[1]
