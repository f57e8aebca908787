"""The twist calibration's per-frame steps, compiled (numba): one pass per session row, so a
session's output does not depend on the batch it is stepped in (`calibration.py` explains the
stage; its numpy functions fit the reference and are what the tests hold these to)."""

from __future__ import annotations

import numpy as np
from numba import njit

from .bn_skeleton import HIPS
from .quaternion import qdot, qexp, qinv, qlog, qmul, qrot, qunit, quat_at

# one session's state row (`state_width`): per joint the sign-aligned sum of its local rotations
# (4), the twist it is to get (a rotation vector, 3) and the twist applied on the latest frame (4);
# then the frames seen
SUM, TARGET, APPLIED, PER_JOINT = 0, 4, 7, 11


def state_width(joints: int) -> int:
    return PER_JOINT * joints + 1


@njit(cache=True, error_model="numpy")
def calibrate_in(rot, parents, axes, deadzone, means, directions, window, ramp, state, out):
    """Each session's input frame rot (B, J, 4) into out with every bone turned about itself by
    its calibration twist; the session's state row (B, `state_width`) advances. The first
    `window` frames are measured (their mean local rotations); then the twists that bring that
    mean onto the reference clip whose bones point most like it (means (K, J, 4), their bones'
    directions (K, J, 3)), less each joint's `deadzone` (radians), are set and ramp in over
    `ramp` frames. A joint with a zero axis (the root, the hips) is not turned."""
    B, J = rot.shape[0], rot.shape[1]
    count = PER_JOINT * J
    for b in range(B):
        n = state[b, count]
        if n < window:
            for j in range(HIPS + 1, J):
                q = qunit(quat_at(rot, b, j))
                o = j * PER_JOINT + SUM
                s = (state[b, o], state[b, o + 1], state[b, o + 2], state[b, o + 3])
                k = -1.0 if qdot(s, q) < 0.0 else 1.0
                for c in range(4):
                    state[b, o + c] += k * q[c]
            if n + 1.0 >= window:
                _set_targets(state, b, parents, axes, deadzone, means, _nearest(state, b, axes, directions))
        if n < window + ramp:
            n += 1.0
            state[b, count] = n
            share = min(max((n - window) / ramp, 0.0), 1.0)
            for j in range(HIPS + 1, J):
                o = j * PER_JOINT
                t = qexp((share * state[b, o + TARGET], share * state[b, o + TARGET + 1], share * state[b, o + TARGET + 2]))
                for c in range(4):
                    state[b, o + APPLIED + c] = t[c]
        for j in range(J):
            q = quat_at(rot, b, j)
            if j > HIPS:
                q = qmul(qmul(qinv(_twist(state, b, parents[j])), q), _twist(state, b, j))
            for c in range(4):
                out[b, j, c] = q[c]


@njit(cache=True, error_model="numpy")
def _set_targets(state, b, parents, axes, deadzone, means, nearest):
    """Session b's twists: per joint (parents first, as a parent's twist turns its child's
    frame), the twist about the bone from its measured mean to the nearest clip's, less the
    dead zone."""
    J = axes.shape[0]
    full = [(0.0, 0.0, 0.0, 1.0)] * J
    for j in range(HIPS + 1, J):
        if axes[j, 0] == 0.0 and axes[j, 1] == 0.0 and axes[j, 2] == 0.0:
            continue
        o = j * PER_JOINT
        mean = qunit((state[b, o + SUM], state[b, o + SUM + 1], state[b, o + SUM + 2], state[b, o + SUM + 3]))
        seen = qmul(qinv(full[parents[j]]), mean)  # the mean once its parent is turned
        d = qlog(qmul(qinv(seen), quat_at(means, nearest, j)))
        along = d[0] * axes[j, 0] + d[1] * axes[j, 1] + d[2] * axes[j, 2]
        along = max(abs(along) - deadzone[j], 0.0) * (1.0 if along > 0.0 else -1.0)
        v = (along * axes[j, 0], along * axes[j, 1], along * axes[j, 2])
        full[j] = qexp(v)
        state[b, o + TARGET], state[b, o + TARGET + 1], state[b, o + TARGET + 2] = v


@njit(cache=True, error_model="numpy")
def calibrate_out(rot, parents, state, out):
    """A model's output frame rot (B, J, 4) turned back onto the session's own twists (the
    inverse of `calibrate_in` with the twists of its latest frame) into out."""
    B, J = rot.shape[0], rot.shape[1]
    for b in range(B):
        for j in range(J):
            q = quat_at(rot, b, j)
            if j > HIPS:
                q = qmul(qmul(_twist(state, b, parents[j]), q), qinv(_twist(state, b, j)))
            for c in range(4):
                out[b, j, c] = q[c]


@njit(cache=True, error_model="numpy")
def _twist(state, b, j):
    """The twist session b applies to joint j's frame (the identity above the hips' children and
    before any is set)."""
    o = j * PER_JOINT + APPLIED
    t = (state[b, o], state[b, o + 1], state[b, o + 2], state[b, o + 3])
    if j <= HIPS or (t[0] == 0.0 and t[1] == 0.0 and t[2] == 0.0 and t[3] == 0.0):
        return (0.0, 0.0, 0.0, 1.0)
    return t


@njit(cache=True, error_model="numpy")
def _nearest(state, b, axes, directions):
    """The reference clip whose bones point most like session b's mean rotations: content
    matched by where the bones point, which a twist does not change."""
    K, J = directions.shape[0], directions.shape[1]
    mine = np.zeros((J, 3))
    for j in range(HIPS + 1, J):
        o = j * PER_JOINT + SUM
        mean = qunit((state[b, o], state[b, o + 1], state[b, o + 2], state[b, o + 3]))
        v = qrot(mean, (axes[j, 0], axes[j, 1], axes[j, 2]))
        mine[j, 0], mine[j, 1], mine[j, 2] = v[0], v[1], v[2]
    best, best_k = -np.inf, 0
    for k in range(K):
        score = 0.0
        for j in range(HIPS + 1, J):
            score += mine[j, 0] * directions[k, j, 0] + mine[j, 1] * directions[k, j, 1] + mine[j, 2] * directions[k, j, 2]
        if score > best:
            best, best_k = score, k
    return best_k
