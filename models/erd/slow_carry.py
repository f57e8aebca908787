"""Carry only the slow part of each rotation through Style-ERD's rotation priors.

The priors (`rotation_prior.py`) map a joint's rotation by a per-style linear map in its tangent
space, with gains above 1 where the style spreads wider than what is carried, and two of them run
one after the other (the leaf prior on the input, the output prior on the network's pose). Each
scaled every frame-to-frame wobble along with the pose: toward feminine on the validation
clips, the p99.9 of the head's rotation acceleration went from 3.1 deg/frame² in the input to 6.3
after the leaf prior and 10.9 in the output, and the head turned faster from one frame to the next
than the style's real p99.9 in 9.3 % of frames (real clips: 0.2-0.4 %). So each prior maps a copy
of the rotation that follows it slowly, and the rest, the fast part, rides on top, never magnified:

    slow_t = nlerp(slow_{t-1}, q_t, SLOW_WEIGHT)          (slow_0 = q_0)
    p_t    = slow_t^-1 q_t                                (the fast part)
    out_t  = bounds(carry(slow_t) (G p_xyz, p_w) / |.|)    (~ carry(slow_t) exp(G log p_t))

G is the prior's map with its gains capped at 1 (`StyleCarry.damping`): the fast part is never
magnified, but where the style moves a joint less than what is carried (elderly's forearms) it
is still shrunk; passed unscaled, elderly's forearm popped more than before. A held pose is
carried exactly as before (slow = q); `bounds`, the prior's clamp, keeps the sum inside the
style's real range. Joints a prior only clamps (the output prior's legs and Hips) are carried
whole: there is nothing to slow. `SLOW_WEIGHT` was chosen on the validation clips (model card:
toward feminine 9.3 -> 3.3 % of frames over the real p99.9 for the head, one validation clip
less in one rotation-judge cell, the step 5-9 % dearer at batches of 256-1000).
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
    """(the rotations q (B, J, 4) carried, the new slow copies) from the slow copies before this
    frame: `gait.carry_by_gait` of the new slow copy, then the fast part on top through `other`'s
    maps with their gains capped at 1 (`StyleCarry.damping`, mixed by the weights; the rest of
    the weight and the Hips, whose fast part holds its turning, pass it as it is), then
    `other`'s clamp; the joints `other` only clamps are carried whole (the same to round-off
    where the slow copy is inside the range). Without priors, q as it is. One compiled pass
    (`style_carry_kernels.carry_slow_batch`); `tests/reference/erd_carry.py` is the reference."""
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
    return kernels.carry_slow(
        q, slow, SLOW_WEIGHT, w, r, other.arrays, then, bounds, bounds, other.damping, other.clamps_only, hips
    )


def clip_carry_slow(
    other: StyleCarry | None,
    run: StyleCarry | None,
    q: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
) -> np.ndarray:
    """`carry_slow` over every frame (T, J, 4) of a clip, as a stream sees it (offline)."""
    before = np.zeros_like(np.asarray(q, np.float64))  # each frame's slow copy before it
    for t in range(1, len(q)):
        before[t] = follow(before[t - 1 : t], q[t - 1 : t])[0]
    return carry_slow(other, run, q, before, weights, share, hips)[0]
