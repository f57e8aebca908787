"""A hinge joint kept on its hinge at no less than its least real bend (`hinge.Hinges`), compiled.

A model linear in rotations (LTI) bends a straightening elbow or knee backward and turns a forearm
off its hinge. Real knees and elbows turn about one axis and never bend past their floor, so the
output's swing becomes a bend about the hinge axis, held at the floor; its twist is kept.
"""

from __future__ import annotations

import math

from numba import njit

from .quaternion import dot3, qinv, qmul


@njit(cache=True, error_model="numpy")
def floor_bend(q, bone, hinge, floor):
    """Unit q's swing replaced by the nearest rotation about `hinge`, bent at least `floor`."""
    along = dot3((q[0], q[1], q[2]), bone)
    norm = math.sqrt(along * along + q[3] * q[3])
    twist = (0.0, 0.0, 0.0, 1.0)  # a half turn off the bone has no twist part
    if norm > 1e-9:
        twist = (along * bone[0] / norm, along * bone[1] / norm, along * bone[2] / norm, q[3] / norm)
    swing = qmul(q, qinv(twist))
    # the nearest rotation about the hinge: the swing's hinge and identity parts, renormalised;
    # its bend 2 atan2(a, w) >= 2 a, so most frames pass the floor test without trigonometry
    a = dot3((swing[0], swing[1], swing[2]), hinge)
    w = swing[3]
    if w < 0.0:
        a, w = -a, -w
    n = math.sqrt(a * a + w * w)
    if n > 1e-12 and ((a >= 0.0 and 2.0 * a >= floor) or 2.0 * math.atan2(a, w) >= floor):
        a, w = a / n, w / n
    else:
        a, w = math.sin(0.5 * floor), math.cos(0.5 * floor)
    return qmul((a * hinge[0], a * hinge[1], a * hinge[2], w), twist)


@njit(cache=True, error_model="numpy")
def floor_bends(rotations, bone, hinge, floor):
    """(F, J, 4) rotations in place, each hinge joint (finite floor) on its hinge, at its floor."""
    for j in range(rotations.shape[1]):
        if not floor[j] > -math.inf:
            continue
        b, h = (bone[j, 0], bone[j, 1], bone[j, 2]), (hinge[j, 0], hinge[j, 1], hinge[j, 2])
        for t in range(rotations.shape[0]):
            q = floor_bend(
                (rotations[t, j, 0], rotations[t, j, 1], rotations[t, j, 2], rotations[t, j, 3]), b, h, floor[j]
            )
            rotations[t, j, 0], rotations[t, j, 1], rotations[t, j, 2], rotations[t, j, 3] = q
    return rotations
