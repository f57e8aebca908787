"""Carry only the slow part of each rotation through Style-ERD's rotation priors.

A prior's gains above 1 would scale every frame-to-frame wobble with the pose (the head turned
faster than anything real), so each prior maps a copy of the rotation that follows it slowly,
and the fast part rides on top, never magnified:

    slow_t = nlerp(slow_{t-1}, q_t, SLOW_WEIGHT)          (slow_0 = q_0)
    p_t    = slow_t^-1 q_t                                (the fast part)
    out_t  = bounds(carry(slow_t) (G p_xyz, p_w) / |.|)    (~ carry(slow_t) exp(G log p_t))

G is the prior's map with its gains capped at 1 (`StyleCarry.damping`); `bounds`, the prior's
clamp, keeps the sum inside the style's real range. A held pose is carried as before; joints a
prior only clamps are carried whole. `SLOW_WEIGHT` was chosen on validation clips (model card).
"""

from __future__ import annotations

import numpy as np

from ..motion import style_carry_kernels as kernels
from ..motion.rotations import quat_inv, quat_mul
from ..motion.style_carry import StyleCarry
from .gait import carry_by_gait

SLOW_WEIGHT = 0.5  # the newest frame's weight in the slow copy (a ~3-frame exponential average)


def follow(slow: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(B, J, 4) the slow copy after this frame's rotations `q`: an exponential average by
    normalised lerp on the shorter arc. A row of zeros (a session's first frame, or a snapshot
    from before this state existed) starts at `q`. (The step computes it inside `carry_slow`.)"""
    slow, q = np.asarray(slow, np.float64), np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    aligned = np.where(np.sum(slow * q, axis=-1, keepdims=True) < 0.0, -slow, slow)
    mixed = (1.0 - SLOW_WEIGHT) * aligned + SLOW_WEIGHT * q
    mixed /= np.maximum(np.linalg.norm(mixed, axis=-1, keepdims=True), 1e-12)
    unset = ~np.any(slow != 0.0, axis=(-1, -2))
    return np.where(unset[..., None, None], q, mixed)


def carry_slow(
    other: StyleCarry | None,
    run: StyleCarry | None,
    q: np.ndarray,
    slow: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
) -> tuple[np.ndarray, np.ndarray]:
    """(the rotations q (B, J, 4) carried, the new slow copies): `gait.carry_by_gait` of the new
    slow copy, the fast part on top through `other`'s gain-capped maps (the Hips' and the unweighted
    share pass as they are), then `other`'s clamp; joints `other` only clamps are carried whole.
    Without priors, q as it is. Compiled (`style_carry_kernels.carry_slow_batch`); the reference is
    `tests/reference/erd_carry.py`."""
    if other is None:  # no range to clamp into: a run prior's carry, the fast part as it is
        new = follow(slow, q)
        if run is None:
            return q, new
        q = np.asarray(q, np.float64)
        fast = quat_mul(quat_inv(new), q / np.linalg.norm(q, axis=-1, keepdims=True))
        fast = np.where(fast[..., 3:] < 0.0, -fast, fast)
        return quat_mul(carry_by_gait(other, run, new, weights, share, hips=hips), fast), new
    w = np.asarray(weights, np.float64)
    r = np.zeros(len(w)) if run is None else np.asarray(share, np.float64)
    bounds = other.bounds.arrays  # the run prior is followed by it, and every output kept in it
    then = other.arrays if run is None else run.arrays
    priors = kernels.SlowPriors(other.arrays, then, bounds, bounds, other.damping, other.clamps_only)
    return kernels.carry_slow(q, slow, SLOW_WEIGHT, w, r, priors, hips)
