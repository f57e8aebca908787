"""`waving_arm.py`'s step compiled (numba), for one session inside LTI's step (`kernels.step`):
each side's running means brought up to this frame and, while the hand is raised and waving,
the arm swung and held in the styles' balls. The numpy reference is in the tests
(`tests/lti_waving_reference.py`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from ..motion.quaternion import nlerp, qdot, qexp, qinv, qlog, qmul, qneg, quat_at, qunit
from ..motion.rotation_ball_kernels import clamp_joint


class WavingArm(NamedTuple):
    """The waving arm's settings (`waving_arm.py`)."""

    joints: np.ndarray  # (2, K) int64: each side's swung joints
    raise_ramp: np.ndarray  # (2,) cm: the hand's height over its shoulder, raise share 0 -> 1
    wave_ramp: np.ndarray  # (2,) cm/s: its sway, wave share 0 -> 1
    level_ramp: np.ndarray  # (2,) cm/s: its rise, level share 1 -> 0
    frames: float  # the running mean's exponential average
    gain: float  # the input's swing, scaled


@njit(cache=True, error_model="numpy")
def _toward(mean, q, fresh, frames):
    """The running mean after q: a normalised step of 1 / frames toward q (sign aligned), or q."""
    if fresh:
        return qunit(q)
    if qdot(q, mean) < 0.0:
        q = qneg(q)
    return qunit(
        (
            mean[0] + (q[0] - mean[0]) / frames,
            mean[1] + (q[1] - mean[1]) / frames,
            mean[2] + (q[2] - mean[2]) / frames,
            mean[3] + (q[3] - mean[3]) / frames,
        )
    )


@njit(cache=True, error_model="numpy")
def ramp(x, lo, hi):
    """0 up to lo, 1 from hi, linear between (`models.motion.hands` shares)."""
    return min(max((x - lo) / (hi - lo), 0.0), 1.0)


@njit(cache=True, error_model="numpy")
def _held(q, j, weights, b, total, prior_mean, prior_radii):
    """q held in each style's ball at joint j, blended by session b's weights (`kernels.translate`
    does the same with every joint)."""
    acc = (0.0, 0.0, 0.0, 0.0)
    for s in range(weights.shape[1]):
        w = weights[b, s]
        if w <= 0.0:
            continue
        p = clamp_joint(q, quat_at(prior_mean, s, j), prior_radii[s, 0, j], prior_radii[s, 1, j], False)
        if qdot(p, q) < 0.0:
            w = -w
        w /= total
        acc = (acc[0] + w * p[0], acc[1] + w * p[1], acc[2] + w * p[2], acc[3] + w * p[3])
    return qunit(acc)


@njit(cache=True, error_model="numpy")
def swing_arms(b, arm, rot_in, rot_out, weights, started, prev_offsets, offsets, swayed, risen, in_mean, out_mean,
               prior_mean, prior_radii, swing, new_in_mean, new_out_mean):  # fmt: skip
    """Session b, each side: the running means of the arm's joints (in_mean, out_mean (B, 2, K,
    4): the input's and the output's) brought up to this frame into new_in_mean, new_out_mean
    (they start afresh at a session's first frame, when the hand was below its raise ramp the
    frame before, or when never set); where `swing`, rot_out's arm turned in place by the share
    raise x wave x level x min(style weight total, 1) toward the output's mean turned by `gain`
    times the input's rotation from its mean, then held in the styles' balls."""
    total = 0.0
    for s in range(weights.shape[1]):
        total += weights[b, s]
    K = arm.joints.shape[1]
    for side in range(2):
        fresh = (not started[b]) or prev_offsets[b, side, 1] <= arm.raise_ramp[0]
        if not fresh:
            unset = True
            for k in range(K):
                for c in range(4):
                    if in_mean[b, side, k, c] != 0.0:
                        unset = False
            fresh = unset
        for k in range(K):
            j = arm.joints[side, k]
            mi = _toward(quat_at(in_mean[b], side, k), quat_at(rot_in, b, j), fresh, arm.frames)
            mo = _toward(quat_at(out_mean[b], side, k), quat_at(rot_out, b, j), fresh, arm.frames)
            for c in range(4):
                new_in_mean[b, side, k, c] = mi[c]
                new_out_mean[b, side, k, c] = mo[c]
        share = ramp(offsets[b, side, 1], arm.raise_ramp[0], arm.raise_ramp[1])
        share *= ramp(swayed[b, side], arm.wave_ramp[0], arm.wave_ramp[1])
        share *= (1.0 - ramp(risen[b, side], arm.level_ramp[0], arm.level_ramp[1])) * min(total, 1.0)
        if not swing or share <= 0.0:
            continue
        for k in range(K):
            j = arm.joints[side, k]
            a = quat_at(rot_out, b, j)
            v = qlog(qmul(qinv(quat_at(new_in_mean[b], side, k)), quat_at(rot_in, b, j)))
            t = qmul(quat_at(new_out_mean[b], side, k), qexp((arm.gain * v[0], arm.gain * v[1], arm.gain * v[2])))
            q = _held(nlerp(a, t, share), j, weights, b, total, prior_mean, prior_radii)
            for c in range(4):
                rot_out[b, j, c] = q[c]
