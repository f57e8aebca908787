"""Compiled `transfer_twist` for the per-frame streaming steps (numba).

The numpy version in `twist.py` is ~25 small array operations per joint: ~1.4 ms for one frame of
22 joints, six times a Style-ERD step. Here one pass over the joints does the same arithmetic on
scalars (~1 us per frame). Self-contained on purpose: numba's on-disk cache does not notice
changes in helpers imported from other files. `twist.py` stays the reference; tests check that
they agree.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

ROOT, FRAME, BONE, LEAF = 0, 1, 2, 3  # joint kinds, as `twist._plan` names them


@njit(cache=True, inline="always")
def _mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


@njit(cache=True, inline="always")
def _inv(q):
    return (-q[0], -q[1], -q[2], q[3])


@njit(cache=True, inline="always")
def _apply(q, v):
    x, y, z, w = q
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + (y * tz - z * ty), v[1] + w * ty + (z * tx - x * tz), v[2] + w * tz + (x * ty - y * tx))


@njit(cache=True, inline="always")
def _unit(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@njit(cache=True, inline="always")
def _between(u, v):
    """Smallest rotation carrying unit u onto unit v (any perpendicular axis when opposite)."""
    d = u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
    q = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0], 1.0 + d)
    if q[3] < 1e-9:
        ax = (0.0, u[2], -u[1])  # u x (1, 0, 0)
        if ax[1] * ax[1] + ax[2] * ax[2] < 1e-12:
            ax = (-u[2], 0.0, u[0])  # u x (0, 1, 0)
        q = (ax[0], ax[1], ax[2], 0.0)
    return _unit(q)


@njit(cache=True, inline="always")
def _row(a, j):
    return (a[j, 0], a[j, 1], a[j, 2], a[j, 3])


@njit(cache=True)
def transfer_twist_batch(kinds, parents, axes, keep, source, pose, out):
    """`twist.transfer_twist` for (B, J, 4) float64 `source` and `pose` into `out`; the plan as
    arrays: kinds (J,) int64, parents (J,) int64, axes (J, 3), keep (J,) bool."""
    J = kinds.shape[0]
    g_pose = np.empty((J, 4))
    g_new = np.empty((J, 4))
    for b in range(pose.shape[0]):
        for j in range(J):
            pj = _unit(_row(pose[b], j))
            if kinds[j] == ROOT:
                for c in range(4):
                    g_pose[j, c] = g_new[j, c] = out[b, j, c] = pj[c]
                continue
            p = parents[j]
            gp = _mul(_row(g_pose, p), pj)
            gn_parent = _row(g_new, p)
            if kinds[j] == FRAME:
                g = gp
            else:
                local = pj if keep[j] else _unit(_row(source[b], j))
                g = _mul(gn_parent, local)
                if kinds[j] == BONE:
                    a = (axes[j, 0], axes[j, 1], axes[j, 2])
                    g = _mul(_between(_apply(g, a), _apply(gp, a)), g)
            loc = _mul(_inv(gn_parent), g)
            for c in range(4):
                g_pose[j, c] = gp[c]
                g_new[j, c] = g[c]
                out[b, j, c] = loc[c]
    return out
