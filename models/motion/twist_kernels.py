"""Compiled `transfer_twist` for the per-frame streaming steps (numba): one pass over the joints
on scalars (~1 us a frame) instead of the reference's (`tests/reference/twist.py`) ~1.4 ms of
small numpy operations.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from .quaternion import axis_angle, between, cross, dot3, qinv, qmul, qrot, qunit, row3, row4, wrap

ROOT, FRAME, BONE, LEAF = 0, 1, 2, 3  # joint kinds, as `twist._plan` names them


class TwistPlan(NamedTuple):
    """A skeleton's plan as the kernel takes it (`twist._kernel_plan`)."""

    kinds: np.ndarray  # (J,) int64, ROOT ... LEAF
    parents: np.ndarray  # (J,) int64
    axes: np.ndarray  # (J, 3) bone axis in each joint's frame
    keep: np.ndarray  # (J,) bool: the joints that take the pose's rotation as it is


@njit(cache=True, error_model="numpy")
def clamped_twist(local, axis, turn, lo, hi):
    """The part of `turn` keeping the twist of `local` in [lo, hi] (or where it is, when outside)."""
    twist = wrap(2.0 * math.atan2(dot3(local, axis), local[3]))
    return min(max(twist + turn, min(lo, twist)), max(hi, twist)) - twist


@njit(cache=True, error_model="numpy")
def hinge_twist(g, g_child, axis, child_axis, bend, lo, hi, fade, local):
    """The turn about its bone laying a joint's hinge child along `bend`, twist kept in [lo, hi]."""
    d = qrot(qinv(g), qrot(g_child, child_axis))  # the child's bone in the joint's frame
    along = dot3(d, axis)
    across = (d[0] - along * axis[0], d[1] - along * axis[1], d[2] - along * axis[2])
    tau = math.atan2(dot3(cross(bend, across), axis), dot3(across, bend))
    return clamped_twist(local, axis, tau * hinge_weight(tau, math.sqrt(dot3(across, across)), fade), lo, hi)


@njit(cache=True, error_model="numpy")
def hinge_weight(tau, across, fade):
    """How much of `tau` to take: none near straight (`fade`) or near a half turn (a backward bend)."""
    straight = min(1.0, across / math.sin(fade)) if fade > 0.0 else 1.0
    return straight * min(1.0, max(0.0, 2.0 - 2.0 * abs(tau) / math.pi))


@njit(cache=True)
def transfer_twist_batch(plan, hinges, source, pose, out):
    """`twist.transfer_twist` for (B, J, 4) float64 `source` and `pose` into `out`."""
    kinds, parents, axes, keep = plan
    hinge_child, bend, mean, limits, fade = hinges
    J = kinds.shape[0]
    g_pose = np.empty((J, 4))
    g_new = np.empty((J, 4))
    turned = np.zeros(J)  # per hinge joint, how far its parent turned about its bone
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
                turn, turned[j] = turned[j], 0.0
                if turn != 0.0 and not keep[j]:  # a hinge joint turns back as far as its twist interval allows
                    a = row3(axes, j)
                    back = clamped_twist(qmul(qinv(row4(mean, j)), local), a, -turn, limits[j, 0], limits[j, 1])
                    local = qmul(local, axis_angle(a, back))
                g = qmul(gn_parent, local)
                if kinds[j] == BONE:
                    a = row3(axes, j)
                    g = qmul(between(qrot(g, a), qrot(gp, a)), g)
                    k = hinge_child[j]
                    if k >= 0 and not keep[j]:
                        g_child = qmul(gp, qunit(row4(pose[b], k)))
                        local = qmul(qinv(row4(mean, j)), qmul(qinv(gn_parent), g))
                        tau = hinge_twist(
                            g, g_child, a, row3(axes, k), row3(bend, j), limits[j, 0], limits[j, 1], fade, local
                        )
                        g = qmul(g, axis_angle(a, tau))
                        turned[k] = tau
            loc = qmul(qinv(gn_parent), g)
            for c in range(4):
                g_pose[j, c] = gp[c]
                g_new[j, c] = g[c]
                out[b, j, c] = loc[c]
    return out
