"""Forward kinematics on the Bandai Namco skeleton, compiled (numba), for the streaming steps of
Style-ERD and LPN-FiLM: world rotations and positions from the Hips translation and local
rotations."""

from __future__ import annotations

import numpy as np
from numba import njit

from .bn_skeleton import HIPS
from .quaternion import qmul, qrot, qunit, row3, row4


@njit(cache=True, error_model="numpy")
def world_pose(root, rotations, parents, offsets, grot, gpos):
    """FK of one frame into grot (J, 4), gpos (J, 3) (rotations normalised, parents first)."""
    for j in range(rotations.shape[0]):
        q = qunit(row4(rotations, j))
        t = (root[0], root[1], root[2]) if j == HIPS else row3(offsets, j)
        p = parents[j]
        if p < 0:
            grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = q
            gpos[j, 0], gpos[j, 1], gpos[j, 2] = t
            continue
        gp = row4(grot, p)
        d = qrot(gp, t)
        gpos[j, 0], gpos[j, 1], gpos[j, 2] = gpos[p, 0] + d[0], gpos[p, 1] + d[1], gpos[p, 2] + d[2]
        grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = qmul(gp, q)


@njit(cache=True, error_model="numpy")
def forward_kinematics(root, rotations, parents, offsets):
    """World rotations (N, J, 4) and positions (N, J, 3) of N frames."""
    n, J = rotations.shape[0], rotations.shape[1]
    grot, gpos = np.empty((n, J, 4)), np.empty((n, J, 3))
    for f in range(n):
        world_pose(root[f], rotations[f], parents, offsets, grot[f], gpos[f])
    return grot, gpos
