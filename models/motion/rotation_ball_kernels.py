"""Compiled rotation ball (`rotation_ball.py`) for streaming steps: one joint of one frame on
4-tuples (`clamp_joint`, used inside LTI's step kernel), and a whole batch of frames under mixed
style weights (`clamp_mixed`, LPN-FiLM). Float64; equal to the numpy reference
(`tests/reference/rotation_ball.py`) to round-off.
"""

from __future__ import annotations

import math

from numba import njit

from .bn_skeleton import HIPS
from .quaternion import dot3, qdot, qinv, qmul, qneg, quat_at, qunit


@njit(cache=True, error_model="numpy")
def clamp_joint(q, mean, inner, outer, hips):
    """One joint held within the style's ball around `mean` (the Hips without their heading)."""
    twist = (0.0, 0.0, 0.0, 1.0)
    if hips:
        n = math.sqrt(q[1] * q[1] + q[3] * q[3])
        if n > 1e-12:
            twist = (0.0, q[1] / n, 0.0, q[3] / n)
        c = qmul(qinv(twist), q)
    else:
        c = q
    rel = qmul(qinv(mean), c)
    if rel[3] < 0.0:
        rel = qneg(rel)
    s = math.sqrt(dot3(rel, rel))
    d = 2.0 * math.atan2(s, rel[3])
    if not d > inner:
        return q
    span = max(outer - inner, 1e-12)
    new_d = min(inner + span * math.tanh((d - inner) / span), outer)
    if not new_d < d:
        return q
    k = math.sin(0.5 * new_d) / max(s, 1e-300)
    c = qmul(mean, (rel[0] * k, rel[1] * k, rel[2] * k, math.cos(0.5 * new_d)))
    return qmul(twist, c) if hips else c


@njit(cache=True, error_model="numpy")
def clamp_mixed(rotations, weights, rest_style, mean, radii, out):
    """Per joint the weighted mean of the rotation held in each style's ball: fades do not jump."""
    B, S = weights.shape
    J = rotations.shape[1]
    for b in range(B):
        total = 0.0
        for s in range(S):
            total += max(weights[b, s], 0.0)
        rest = max(1.0 - total, 0.0)
        base, base_w = 0, -1.0
        for s in range(S):
            w = max(weights[b, s], 0.0) + (rest if s == rest_style else 0.0)
            if w > base_w:
                base, base_w = s, w
        for c in range(4):
            out[b, 0, c] = rotations[b, 0, c]
        for j in range(1, J):
            q = qunit(quat_at(rotations, b, j))
            ref = clamp_joint(q, quat_at(mean, base, j), radii[base, 0, j], radii[base, 1, j], j == HIPS)
            acc = (0.0, 0.0, 0.0, 0.0)
            for s in range(S):
                w = max(weights[b, s], 0.0) + (rest if s == rest_style else 0.0)
                if w <= 0.0:
                    continue
                p = ref if s == base else clamp_joint(q, quat_at(mean, s, j), radii[s, 0, j], radii[s, 1, j], j == HIPS)
                if qdot(p, ref) < 0.0:
                    w = -w
                acc = (acc[0] + w * p[0], acc[1] + w * p[1], acc[2] + w * p[2], acc[3] + w * p[3])
            n = math.sqrt(qdot(acc, acc))
            if n < 1e-12:
                acc, n = ref, 1.0
            for c in range(4):
                out[b, j, c] = acc[c] / n
