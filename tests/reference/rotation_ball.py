"""The rotation ball (`models.motion.rotation_ball`) in numpy over whole arrays: the reference
the compiled clamp (`models.motion.rotation_ball_kernels`) is tested against."""

from __future__ import annotations

import numpy as np

from models.motion.bn_skeleton import HIPS
from models.motion.rotation_ball import up_twist
from models.motion.rotations import quat_inv, quat_mul


def saturate(d: np.ndarray, inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """The clamped distance d' (see `rotation_ball`'s docstring); `inner`/`outer` broadcast with d."""
    with np.errstate(invalid="ignore"):  # inf radii (no prior): d stays
        span = np.maximum(outer - inner, 1e-12)
        soft = inner + span * np.tanh((d - inner) / span)
    return np.where(d > inner, np.minimum(soft, outer), d)


def clamp_rotations(rotations: np.ndarray, mean: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(..., J, 4) local rotations (the Hips with or without its heading) held inside the ball
    (`fit_prior`); a rotation inside the inner radius is returned unchanged."""
    q = np.array(rotations, float, copy=True)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    twist = up_twist(q[..., HIPS, :])
    q[..., HIPS, :] = quat_mul(quat_inv(twist), q[..., HIPS, :])
    rel = quat_mul(quat_inv(mean), q)  # rotation from the mean, taken with w >= 0 (the short way)
    rel = np.where(rel[..., 3:] < 0, -rel, rel)
    s = np.linalg.norm(rel[..., :3], axis=-1)
    d = 2.0 * np.arctan2(s, rel[..., 3])
    new_d = saturate(d, radii[0], radii[1])
    moved = new_d < d
    axis = rel[..., :3] / np.maximum(s, 1e-300)[..., None]
    half = 0.5 * new_d[..., None]
    clamped = quat_mul(mean, np.concatenate([axis * np.sin(half), np.cos(half)], axis=-1))
    q = np.where(moved[..., None], clamped, q)
    q[..., HIPS, :] = quat_mul(twist, q[..., HIPS, :])
    # rotations that were not moved are returned exactly as given (same sign, no round trip)
    return np.where(moved[..., None], q, rotations)
