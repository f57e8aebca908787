"""Compiled per-frame interpolation for `rate.py` (numba): numpy's ~40 operations a call are too
slow for a crowd tick. The parabola runs through the quaternions themselves, normalised (within a
degree of the tangent-space one); row by row, so a crowd's character equals the session alone.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .quaternion import qdot, qneg, quat_at, qunit


@njit(cache=True)
def _copy_row(root, rot, out_root, out_rot):
    """Element by element: an array assignment would compile numpy's broadcasting (seconds)."""
    for c in range(3):
        out_root[c] = root[c]
    for j in range(rot.shape[0]):
        for c in range(4):
            out_rot[j, c] = rot[j, c]


@njit(cache=True)
def interpolate_rows(roots, rotations, u, out_root, out_rot):
    """`rate.interpolate` into out_root, out_rot; u == 1 copies the latest output."""
    n, num_joints = rotations.shape[0], rotations.shape[2]
    for i in range(n):
        x = u[i]
        if x >= 1.0:
            _copy_row(roots[i, 2], rotations[i, 2], out_root[i], out_rot[i])
            continue
        before, now, after = x * (x - 1.0) / 2.0, 1.0 - x * x, x * (x + 1.0) / 2.0
        for c in range(3):
            out_root[i, c] = before * roots[i, 0, c] + now * roots[i, 1, c] + after * roots[i, 2, c]
        q0, q1, q2 = rotations[i, 0], rotations[i, 1], rotations[i, 2]
        for j in range(num_joints):
            # the parabola through the three quaternions (the outer two on the middle one's side), normalised
            s0 = (
                before
                if q0[j, 0] * q1[j, 0] + q0[j, 1] * q1[j, 1] + q0[j, 2] * q1[j, 2] + q0[j, 3] * q1[j, 3] >= 0
                else -before
            )
            s2 = (
                after
                if q2[j, 0] * q1[j, 0] + q2[j, 1] * q1[j, 1] + q2[j, 2] * q1[j, 2] + q2[j, 3] * q1[j, 3] >= 0
                else -after
            )
            x0 = s0 * q0[j, 0] + now * q1[j, 0] + s2 * q2[j, 0]
            x1 = s0 * q0[j, 1] + now * q1[j, 1] + s2 * q2[j, 1]
            x2 = s0 * q0[j, 2] + now * q1[j, 2] + s2 * q2[j, 2]
            x3 = s0 * q0[j, 3] + now * q1[j, 3] + s2 * q2[j, 3]
            out_rot[i, j, 0], out_rot[i, j, 1], out_rot[i, j, 2], out_rot[i, j, 3] = qunit((x0, x1, x2, x3))


@njit(cache=True)
def blend_rows(root0, rot0, root1, rot1, w, out_root, out_rot):
    """`rate.blend` into out_root, out_rot (slerp the shorter way)."""
    n, num_joints = rot1.shape[0], rot1.shape[1]
    for i in range(n):
        t = w[i]
        if t >= 1.0 or t <= 0.0:
            _copy_row(root1[i] if t >= 1.0 else root0[i], rot1[i] if t >= 1.0 else rot0[i], out_root[i], out_rot[i])
            continue
        for c in range(3):
            out_root[i, c] = root0[i, c] + t * (root1[i, c] - root0[i, c])
        for j in range(num_joints):
            a, b = qunit(quat_at(rot0, i, j)), qunit(quat_at(rot1, i, j))
            dot = qdot(a, b)
            if dot < 0.0:
                b, dot = qneg(b), -dot
            dot = min(dot, 1.0)
            theta = math.acos(dot)
            s = math.sin(theta)
            if s < 1e-6:
                w0, w1 = 1.0 - t, t
            else:
                w0, w1 = math.sin((1.0 - t) * theta) / s, math.sin(t * theta) / s
            q = qunit((w0 * a[0] + w1 * b[0], w0 * a[1] + w1 * b[1], w0 * a[2] + w1 * b[2], w0 * a[3] + w1 * b[3]))
            out_rot[i, j, 0], out_rot[i, j, 1], out_rot[i, j, 2], out_rot[i, j, 3] = q


def warm() -> None:
    """Load (or compile) both kernels before the first session rather than on its first frame."""
    roots, rots = np.zeros((1, 3, 3)), np.zeros((1, 3, 1, 4))
    rots[..., 3] = 1.0
    interpolate_rows(roots, rots, np.full(1, 0.5), np.empty((1, 3)), np.empty((1, 1, 4)))
    blend_rows(roots[:, 0], rots[:, 0], roots[:, 1], rots[:, 1], np.full(1, 0.5), np.empty((1, 3)), np.empty((1, 1, 4)))
