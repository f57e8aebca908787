"""Analytic two-bone leg IK in numpy, vectorised over legs with per-leg bone offsets (the LPN foot
lock pins both legs of many sessions in one call). Same construction as the LTI foot lock: bend
thigh and knee in the leg plane to reach the target distance, swing the leg onto the target, keep
the foot's world orientation."""

from __future__ import annotations

import numpy as np

from ..motion.rotations import cross, quat_apply, quat_inv, quat_mul


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    h = 0.5 * angle[..., None]
    return np.concatenate([_unit(axis) * np.sin(h), np.cos(h)], axis=-1)


def _rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Shortest-arc quaternion taking direction u to direction v."""
    u, v = _unit(u), _unit(v)
    q = np.concatenate([cross(u, v), 1.0 + np.sum(u * v, -1, keepdims=True)], axis=-1)
    return q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)


def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(np.sum(_unit(u) * _unit(v), -1), -1.0, 1.0))


def two_bone_ik(gh: np.ndarray, r_up: np.ndarray, r_low: np.ndarray, r_foot: np.ndarray, hip: np.ndarray,
                off_low: np.ndarray, off_foot: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """gh (K, 4): world rotation of the hips; r_* (K, 4): local rotations of upper leg, lower leg,
    foot; hip (K, 3): world hip-joint position; off_low, off_foot (K, 3): knee and ankle offsets;
    target (K, 3): wanted ankle position. Returns the new local (r_up, r_low, r_foot); the ankle
    lands on the target as far as the bone lengths allow."""
    ga = quat_mul(gh, r_up)
    gb = quat_mul(ga, r_low)
    gf = quat_mul(gb, r_foot)
    knee = hip + quat_apply(ga, off_low)
    ankle = knee + quat_apply(gb, off_foot)
    lab, lcb = np.linalg.norm(off_low, axis=-1), np.linalg.norm(off_foot, axis=-1)
    lat = np.clip(np.linalg.norm(target - hip, axis=-1), 1e-3, lab + lcb - 1e-3)
    hip_now, knee_now = _angle(ankle - hip, knee - hip), _angle(hip - knee, ankle - knee)
    hip_want = np.arccos(np.clip((lcb ** 2 - lab ** 2 - lat ** 2) / (-2 * lab * lat), -1, 1))
    knee_want = np.arccos(np.clip((lat ** 2 - lab ** 2 - lcb ** 2) / (-2 * lab * lcb), -1, 1))
    axis = cross(ankle - hip, knee - hip)
    ga2 = quat_mul(_axis_angle(axis, hip_want - hip_now), ga)
    gb2 = quat_mul(_axis_angle(axis, knee_want - knee_now), quat_mul(ga2, r_low))
    knee2 = hip + quat_apply(ga2, off_low)
    ankle2 = knee2 + quat_apply(gb2, off_foot)
    swing = _rotation_between(ankle2 - hip, target - hip)
    ga3, gb3 = quat_mul(swing, ga2), quat_mul(swing, gb2)
    return quat_mul(quat_inv(gh), ga3), quat_mul(quat_inv(ga3), gb3), quat_mul(quat_inv(gb3), gf)
