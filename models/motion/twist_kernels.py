"""Compiled `transfer_twist` for the per-frame streaming steps (numba).

In numpy (`tests/reference/twist.py`, the reference the tests hold it to) it is ~25 small array
operations per joint: ~1.4 ms for one frame of 22 joints, six times a Style-ERD step. Here one pass
over the joints does the same arithmetic on scalars (~1 us per frame).
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
    """The part of `turn` (radians about `axis`) that keeps the twist of `local` (a local rotation
    relative to its real mean) inside [lo, hi], or where it already is when outside."""
    twist = wrap(2.0 * math.atan2(dot3(local, axis), local[3]))
    return min(max(twist + turn, min(lo, twist)), max(hi, twist)) - twist


@njit(cache=True, error_model="numpy")
def hinge_twist(g, g_child, axis, child_axis, bend, lo, hi, fade, local):
    """The angle (radians) to turn a joint of global rotation `g` about its own bone `axis` so
    that its hinge child's bone (global rotation `g_child`, bone `child_axis`) lies along `bend`
    across it (`models.motion.hinge`), weighted by `hinge_weight`, and the joint's
    twist (of `local`, its local rotation relative to its real mean) kept in [lo, hi] (or where
    it already is)."""
    d = qrot(qinv(g), qrot(g_child, child_axis))  # the child's bone in the joint's frame
    along = dot3(d, axis)
    across = (d[0] - along * axis[0], d[1] - along * axis[1], d[2] - along * axis[2])
    tau = math.atan2(dot3(cross(bend, across), axis), dot3(across, bend))
    return clamped_twist(local, axis, tau * hinge_weight(tau, math.sqrt(dot3(across, across)), fade), lo, hi)


@njit(cache=True, error_model="numpy")
def hinge_weight(tau, across, fade):
    """How much of the turn `tau` to take: none as the limb straightens (`across`, the sine of its
    bend, below the sine of `fade`), and none as the turn nears a half turn (the model bends the
    joint backward; `tau` = +-pi are one pose, and a clamp that took either limit would jump)."""
    straight = min(1.0, across / math.sin(fade)) if fade > 0.0 else 1.0
    return straight * min(1.0, max(0.0, 2.0 - 2.0 * abs(tau) / math.pi))


@njit(cache=True)
def transfer_twist_batch(plan, hinges, source, pose, out):
    """`twist.transfer_twist` for (B, J, 4) float64 `source` and `pose` into `out`; the plan a
    `TwistPlan`, the hinges a `hinge.KernelHinges`."""
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
