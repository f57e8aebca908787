"""`hands.hand_offsets_of` and the sway step compiled (numba): forward kinematics over the arm
chains and the sway's average, per row. In numpy they cost ~0.45 ms a step at batch 1 (eight times
LTI's whole step); this is a few microseconds. Self-contained: numba's disk cache only sees this
file."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def _mul(ax, ay, az, aw, bx, by, bz, bw):
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


@njit(cache=True, error_model="numpy")
def _apply(x, y, z, w, vx, vy, vz):
    """v turned by the unit quaternion (x, y, z, w): v + 2w (u x v) + 2 u x (u x v)."""
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


@njit(cache=True, error_model="numpy")
def hand_step(
    rot,
    parents,
    offsets,
    chain,
    hands,
    shoulders,
    prev,
    before,
    rise_before,
    started,
    fps,
    frames,
    above,
    out,
    swayed,
    risen,
):
    """Per row b of local rotations rot (B, J, 4): each hand's offset from its shoulder (out
    (B, 2, 3)) by forward kinematics over `chain` (joint indices, parents first; the chain's root
    at the origin), and its sway and rise after this frame (swayed, risen (B, 2): the horizontal
    and the vertical speed) from the averages before (`before`, `rise_before`) and the previous
    frame's offsets `prev`, averaged over `frames`. A row has no previous frame (its averages
    are 0) unless `started`, or when `prev` is all zeros (a hand is never at its shoulder: a state
    from before the meter). Returns whether any hand is higher than `above` over its shoulder."""
    J = rot.shape[1]
    g = np.empty((J, 4))
    p = np.empty((J, 3))
    raised = False
    for b in range(rot.shape[0]):
        has_prev = False
        if started[b]:
            for s in range(2):
                for k in range(3):
                    if prev[b, s, k] != 0.0:
                        has_prev = True
        for j in chain:
            x, y, z, w = rot[b, j, 0], rot[b, j, 1], rot[b, j, 2], rot[b, j, 3]
            n = math.sqrt(x * x + y * y + z * z + w * w)
            x, y, z, w = x / n, y / n, z / n, w / n
            a = parents[j]
            if a < 0:
                g[j, 0], g[j, 1], g[j, 2], g[j, 3] = x, y, z, w
                p[j, 0], p[j, 1], p[j, 2] = 0.0, 0.0, 0.0
            else:
                g[j, 0], g[j, 1], g[j, 2], g[j, 3] = _mul(g[a, 0], g[a, 1], g[a, 2], g[a, 3], x, y, z, w)
                ox, oy, oz = _apply(g[a, 0], g[a, 1], g[a, 2], g[a, 3], offsets[j, 0], offsets[j, 1], offsets[j, 2])
                p[j, 0], p[j, 1], p[j, 2] = p[a, 0] + ox, p[a, 1] + oy, p[a, 2] + oz
        for s in range(2):
            for k in range(3):
                out[b, s, k] = p[hands[s], k] - p[shoulders[s], k]
            if out[b, s, 1] > above:
                raised = True
            if has_prev:
                dx, dz = out[b, s, 0] - prev[b, s, 0], out[b, s, 2] - prev[b, s, 2]
                speed = math.sqrt(dx * dx + dz * dz) * fps
                swayed[b, s] = before[b, s] + (speed - before[b, s]) / frames
                vertical = abs(out[b, s, 1] - prev[b, s, 1]) * fps
                risen[b, s] = rise_before[b, s] + (vertical - rise_before[b, s]) / frames
            else:
                swayed[b, s] = 0.0
                risen[b, s] = 0.0
    return raised
