"""`waving_arm.py`'s step compiled (numba): per row and side, the running means brought up to this
frame and, while the hand is raised and waving, the arm swung and held in the styles' balls. In
numpy it cost ~0.35 ms a step at batch 1 on a wave (three times LTI's whole step); the numpy
functions in `waving_arm.py` are its reference (tests).

numba's on-disk cache of this file does not see `rotation_ball_kernels.clamp_joint`'s: after
editing that file, clear this file's `__pycache__` entries too.
"""

from __future__ import annotations

import math

from numba import njit

from ..motion.rotation_ball_kernels import clamp_joint, qinv, qmul


@njit(cache=True, error_model="numpy")
def _log(q):
    """Rotation vector of a unit quaternion, shortest arc (`style_carry.quat_log`)."""
    x, y, z, w = q
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 * math.atan2(s, w) / max(s, 1e-12) if s > 1e-9 else 2.0
    return (x * scale, y * scale, z * scale)


@njit(cache=True, error_model="numpy")
def _exp(v):
    """Unit quaternion of a rotation vector (`style_carry.quat_exp`)."""
    angle = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    scale = math.sin(0.5 * angle) / max(angle, 1e-12) if angle > 1e-9 else 0.5
    return (v[0] * scale, v[1] * scale, v[2] * scale, math.cos(0.5 * angle))


@njit(cache=True, error_model="numpy")
def _unit(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@njit(cache=True, error_model="numpy")
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


@njit(cache=True, error_model="numpy")
def _toward(mean, q, fresh, frames):
    """The running mean after q: a normalised step of 1 / frames toward q (sign aligned), or q."""
    if fresh:
        return _unit(q)
    if _dot(q, mean) < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return _unit(
        (
            mean[0] + (q[0] - mean[0]) / frames,
            mean[1] + (q[1] - mean[1]) / frames,
            mean[2] + (q[2] - mean[2]) / frames,
            mean[3] + (q[3] - mean[3]) / frames,
        )
    )


@njit(cache=True, error_model="numpy")
def _ramp(x, lo, hi):
    return min(max((x - lo) / (hi - lo), 0.0), 1.0)


@njit(cache=True, error_model="numpy")
def waving_step(
    rot_in,
    rot_out,
    weights,
    started,
    prev_offsets,
    offsets,
    swayed,
    risen,
    in_mean,
    out_mean,
    prior_mean,
    prior_radii,
    arm,
    raise_ramp,
    wave_ramp,
    level_ramp,
    frames,
    gain,
    swing,
    new_in_mean,
    new_out_mean,
):
    """Per row b and side: the running means of the arm joints `arm` (2, K) brought up to this
    frame (new_in_mean, new_out_mean (B, 2, K, 4)) and, where `swing`, rot_out's arm turned in
    place as `waving_arm.swung` does, by the share raise x wave x level x min(style weight
    total, 1)."""
    B, S = weights.shape
    K = arm.shape[1]
    for b in range(B):
        total = 0.0
        for s in range(S):
            total += weights[b, s]
        for side in range(2):
            fresh = (not started[b]) or prev_offsets[b, side, 1] <= raise_ramp[0]
            if not fresh:
                unset = True
                for k in range(K):
                    for c in range(4):
                        if in_mean[b, side, k, c] != 0.0:
                            unset = False
                fresh = unset
            for k in range(K):
                j = arm[side, k]
                qi = (rot_in[b, j, 0], rot_in[b, j, 1], rot_in[b, j, 2], rot_in[b, j, 3])
                qo = (rot_out[b, j, 0], rot_out[b, j, 1], rot_out[b, j, 2], rot_out[b, j, 3])
                mi = (in_mean[b, side, k, 0], in_mean[b, side, k, 1], in_mean[b, side, k, 2], in_mean[b, side, k, 3])
                mo = (
                    out_mean[b, side, k, 0],
                    out_mean[b, side, k, 1],
                    out_mean[b, side, k, 2],
                    out_mean[b, side, k, 3],
                )
                mi, mo = _toward(mi, qi, fresh, frames), _toward(mo, qo, fresh, frames)
                for c in range(4):
                    new_in_mean[b, side, k, c] = mi[c]
                    new_out_mean[b, side, k, c] = mo[c]
            share = _ramp(offsets[b, side, 1], raise_ramp[0], raise_ramp[1])
            share *= _ramp(swayed[b, side], wave_ramp[0], wave_ramp[1])
            share *= (1.0 - _ramp(risen[b, side], level_ramp[0], level_ramp[1])) * min(total, 1.0)
            if not swing or share <= 0.0:
                continue
            for k in range(K):
                j = arm[side, k]
                qi = (rot_in[b, j, 0], rot_in[b, j, 1], rot_in[b, j, 2], rot_in[b, j, 3])
                a = (rot_out[b, j, 0], rot_out[b, j, 1], rot_out[b, j, 2], rot_out[b, j, 3])
                mi = (
                    new_in_mean[b, side, k, 0],
                    new_in_mean[b, side, k, 1],
                    new_in_mean[b, side, k, 2],
                    new_in_mean[b, side, k, 3],
                )
                mo = (
                    new_out_mean[b, side, k, 0],
                    new_out_mean[b, side, k, 1],
                    new_out_mean[b, side, k, 2],
                    new_out_mean[b, side, k, 3],
                )
                v = _log(qmul(qinv(mi), qi))
                t = qmul(mo, _exp((gain * v[0], gain * v[1], gain * v[2])))
                if _dot(t, a) < 0.0:
                    t = (-t[0], -t[1], -t[2], -t[3])
                q = _unit(
                    (
                        (1.0 - share) * a[0] + share * t[0],
                        (1.0 - share) * a[1] + share * t[1],
                        (1.0 - share) * a[2] + share * t[2],
                        (1.0 - share) * a[3] + share * t[3],
                    )
                )
                acc = (0.0, 0.0, 0.0, 0.0)
                for s in range(S):
                    w = weights[b, s]
                    if w <= 0.0:
                        continue
                    m = (prior_mean[s, j, 0], prior_mean[s, j, 1], prior_mean[s, j, 2], prior_mean[s, j, 3])
                    p = clamp_joint(q, m, prior_radii[s, 0, j], prior_radii[s, 1, j], False)
                    if _dot(p, q) < 0.0:
                        w = -w
                    w /= total
                    acc = (acc[0] + w * p[0], acc[1] + w * p[1], acc[2] + w * p[2], acc[3] + w * p[3])
                acc = _unit(acc)
                for c in range(4):
                    rot_out[b, j, c] = acc[c]
