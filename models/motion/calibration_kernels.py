"""The posture calibration's per-frame steps, compiled (numba): one pass per session row, so a
session's output does not depend on its batch (`calibration.py` explains the stage)."""

from __future__ import annotations

from numba import njit

from .bn_skeleton import HIPS
from .quaternion import qdot, qexp, qinv, qlog, qmul, quat_at, qunit, row4

# one session's state row: per joint the rotation sum (4), target turn (3), latest turn (4); frames seen
SUM, TARGET, APPLIED, PER_JOINT = 0, 4, 7, 11


def state_width(joints: int) -> int:
    return PER_JOINT * joints + 1


@njit(cache=True, error_model="numpy")
def calibrate_in(rot, reference, lo, hi, window, ramp, state, out):
    """Input frames turned into the model's range (measured over `window`, ramped over `ramp`)."""
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
                _set_targets(state, b, reference, lo, hi)
        if n < window + ramp:
            n += 1.0
            state[b, count] = n
            share = min(max((n - window) / ramp, 0.0), 1.0)
            for j in range(HIPS + 1, J):
                o = j * PER_JOINT
                t = qexp(
                    (share * state[b, o + TARGET], share * state[b, o + TARGET + 1], share * state[b, o + TARGET + 2])
                )
                for c in range(4):
                    state[b, o + APPLIED + c] = t[c]
        for j in range(J):
            q = quat_at(rot, b, j)
            if j > HIPS:
                q = qmul(_turn(state, b, j), q)
            for c in range(4):
                out[b, j, c] = q[c]


@njit(cache=True, error_model="numpy")
def _set_targets(state, b, reference, lo, hi):
    """Session b's turns: per joint, from its measured mean to the nearest in-range rotation."""
    for j in range(HIPS + 1, reference.shape[0]):
        o = j * PER_JOINT
        mean = qunit((state[b, o + SUM], state[b, o + SUM + 1], state[b, o + SUM + 2], state[b, o + SUM + 3]))
        r = qlog(qmul(qinv(row4(reference, j)), mean))
        kept = (
            min(max(r[0], lo[j, 0]), hi[j, 0]),
            min(max(r[1], lo[j, 1]), hi[j, 1]),
            min(max(r[2], lo[j, 2]), hi[j, 2]),
        )
        v = qlog(qmul(qmul(row4(reference, j), qexp(kept)), qinv(mean)))
        state[b, o + TARGET], state[b, o + TARGET + 1], state[b, o + TARGET + 2] = v


@njit(cache=True, error_model="numpy")
def calibrate_out(rot, state, out):
    """A model's output frame turned back onto the session's own posture (inverse of `calibrate_in`)."""
    B, J = rot.shape[0], rot.shape[1]
    for b in range(B):
        for j in range(J):
            q = quat_at(rot, b, j)
            if j > HIPS:
                q = qmul(qinv(_turn(state, b, j)), q)
            for c in range(4):
                out[b, j, c] = q[c]


@njit(cache=True, error_model="numpy")
def _turn(state, b, j):
    """The turn session b applies to joint j (the identity before any is set)."""
    o = j * PER_JOINT + APPLIED
    t = (state[b, o], state[b, o + 1], state[b, o + 2], state[b, o + 3])
    if t[0] == 0.0 and t[1] == 0.0 and t[2] == 0.0 and t[3] == 0.0:
        return (0.0, 0.0, 0.0, 1.0)
    return t
