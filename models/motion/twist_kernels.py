"""Compiled `transfer_twist` for the per-frame streaming steps (numba).

In numpy (`tests/reference/twist.py`, the reference the tests hold it to) it is ~25 small array
operations per joint: ~1.4 ms for one frame of 22 joints, six times a Style-ERD step. Here one pass
over the joints does the same arithmetic on scalars (~1 us per frame).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .quaternion import between, qinv, qmul, qrot, qunit, row4

ROOT, FRAME, BONE, LEAF = 0, 1, 2, 3  # joint kinds, as `twist._plan` names them


@njit(cache=True)
def transfer_twist_batch(kinds, parents, axes, keep, source, pose, out):
    """`twist.transfer_twist` for (B, J, 4) float64 `source` and `pose` into `out`; the plan as
    arrays: kinds (J,) int64, parents (J,) int64, axes (J, 3), keep (J,) bool."""
    J = kinds.shape[0]
    g_pose = np.empty((J, 4))
    g_new = np.empty((J, 4))
    for b in range(pose.shape[0]):
        for j in range(J):
            pj = qunit(row4(pose[b], j))
            if kinds[j] == ROOT:
                for c in range(4):
                    g_pose[j, c] = g_new[j, c] = out[b, j, c] = pj[c]
                continue
            p = parents[j]
            gp = qmul(row4(g_pose, p), pj)
            gn_parent = row4(g_new, p)
            if kinds[j] == FRAME:
                g = gp
            else:
                local = pj if keep[j] else qunit(row4(source[b], j))
                g = qmul(gn_parent, local)
                if kinds[j] == BONE:
                    a = (axes[j, 0], axes[j, 1], axes[j, 2])
                    g = qmul(between(qrot(g, a), qrot(gp, a)), g)
            loc = qmul(qinv(gn_parent), g)
            for c in range(4):
                g_pose[j, c] = gp[c]
                g_new[j, c] = g[c]
                out[b, j, c] = loc[c]
    return out
