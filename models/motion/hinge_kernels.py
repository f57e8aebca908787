"""A hinge joint held at its least real bend (`hinge.Hinges.floor`), compiled (numba).

Why: a model that is linear in rotations (LTI) carries a joint that straightens past straight
into a backward bend (an elbow at -27 degrees, a knee flipping back), a pose no real limb takes.
Real knees and elbows of every style never bend backward past their floor (fitted from real
rotations), so the output's bend about the hinge axis is held at the floor; its twist about the
bone and its swing off the hinge axis are kept. Offline (`floor_bends`) and per frame
(`floor_bend`) are the same arithmetic.
"""

from __future__ import annotations

import math

from numba import njit

from .quaternion import dot3, qexp, qinv, qlog, qmul


@njit(cache=True, error_model="numpy")
def floor_bend(q, bone, hinge, floor):
    """Unit q (a joint's local rotation, 4-tuple) with its swing's bend about `hinge` (the swing
    off `bone`, q = swing * twist) raised to `floor` where it is below; q itself otherwise."""
    along = dot3((q[0], q[1], q[2]), bone)
    norm = math.sqrt(along * along + q[3] * q[3])
    twist = (0.0, 0.0, 0.0, 1.0)  # a half turn off the bone has no twist part
    if norm > 1e-9:
        twist = (along * bone[0] / norm, along * bone[1] / norm, along * bone[2] / norm, q[3] / norm)
    swing = qmul(q, qinv(twist))
    # the bend is the swing axis's part along the hinge times angle / sin(angle / 2) (`qlog`),
    # which is at least 2: a part at least floor / 2 (and not negative) is at the floor or past
    # it, found without the arc tangent (most frames: a knee or an elbow bent forward)
    d = dot3((swing[0], swing[1], swing[2]), hinge)
    if swing[3] < 0.0:
        d = -d
    if d >= 0.0 and 2.0 * d >= floor:
        return q
    v = qlog(swing)
    b = dot3(v, hinge)
    if not b < floor:
        return q
    k = floor - b
    return qmul(qexp((v[0] + k * hinge[0], v[1] + k * hinge[1], v[2] + k * hinge[2])), twist)


@njit(cache=True, error_model="numpy")
def floor_bends(rotations, bone, hinge, floor):
    """(F, J, 4) local rotations, in place: every hinge joint (finite `floor[j]`) held at its floor."""
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
