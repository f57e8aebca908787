"""LTI's streaming step, compiled (numba): one call per frame for every session.

`step` reads top to bottom: `translate` (the LTI systems of all a style's sessions at once, each
style's rotation ball and hinge floor), the hands measured, `carry_raised_arms`, the feet planted.
Compiled in one call because a frame's few thousand multiply-adds cost less than ~1,000 numpy
calls. [A; C] is block diagonal (sparse); [B; D]'s rows fall in groups reading the same inputs,
each a dense product (~40 % fewer multiply-adds). Records travel packed (`CARRY`, `pack`).

Everything is float64; the results equal the numpy formulas (the offline path) to round-off.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from ..motion.bn_skeleton import HIPS, NUM_JOINTS
from ..motion.feet import STATE_SHAPES as FEET_STATE
from ..motion.feet_kernels import PITCH_SHARE, Feet, follow_pitch, plant_feet
from ..motion.hands_kernels import Hands, hand_step
from ..motion.hinge_kernels import floor_bend
from ..motion.novelty_kernels import fade_step
from ..motion.quaternion import nlerp, qdot, qexp, qinv, qlog, qmul, quat_at, qunit, qyaw, row3, row4, turn_y, wrap
from ..motion.rotation_ball_kernels import clamp_joint
from ..motion.style_carry_kernels import carry_batch

FEATURE_DIM = 67  # root displacement (2), yaw change, height, 21 expmaps
SHARE_FLOOR = 1e-3  # an eased raised-arm share below this is 0 (`raised_shares`)
GROUP_MIN_SAVING = 500  # multiply-adds a group of rows must save to get its own product (a call costs ~that)
CHUNK = 32  # sessions whose LTI step is computed together: their inputs and outputs (~50 kB) stay in cache

# --------------------------------------------------------------------------- records


class Frame(NamedTuple):
    root: np.ndarray  # (B, 3) the input's Hips position
    rotations: np.ndarray  # (B, J, 4) its local rotations
    weights: np.ndarray  # (B, S) style weights
    x_at: np.ndarray  # (S,) int64: where each style's LTI state sits in `Session.x` (-1: no session uses the style)


class Output(NamedTuple):
    root: np.ndarray  # (B, 3)
    rotations: np.ndarray  # (B, J, 4)
    contacts: np.ndarray  # (B, 2) bool: planted legs, or the footplant classifier's without the planter


class Session(NamedTuple):
    """Per-session state besides the planter's `Feet`: views of the packed carry (flags 0.0 / 1.0)."""

    started: np.ndarray  # (B,) a frame was seen
    in_yaw: np.ndarray  # (B,) the input's heading the frame before
    in_ground: np.ndarray  # (B, 2) and its ground position
    out_yaw: np.ndarray  # (B,) the output's heading
    out_ground: np.ndarray  # (B, 2) and its ground position
    blend: np.ndarray  # (B, 3) the erf blend weight's eased history: set (1.0) or not, its fast and slow follower
    raise_share: np.ndarray  # (B, 2, 2) each side's raised-arm share eased (`ease`): its fast and slow follower
    hand_prev: np.ndarray  # (B, 2, 3) the input's hands from their shoulders, the frame before
    hand_sway: np.ndarray  # (B, 2) their horizontal speed, averaged
    hand_rise: np.ndarray  # (B, 2) their vertical speed, averaged
    x: np.ndarray  # (B, n) the LTI states of the styles in use side by side (`Frame.x_at`)


# A session's carry (`Session` less x, then `Feet`) packed in one float64 row: a few arrays a step, not ~20.
CARRY = {
    "started": (),
    "in_yaw": (),
    "in_ground": (2,),
    "out_yaw": (),
    "out_ground": (2,),
    "blend": (3,),
    "raise_share": (2, 2),
    "hand_prev": (2, 3),
    "hand_sway": (2,),
    "hand_rise": (2,),
    **{key: shape for key, (shape, _) in FEET_STATE.items()},
}


def _layout() -> tuple[dict[str, tuple], int]:
    """Each carry entry's (first column, shape, C strides in bytes) in the packed row; the width."""
    spans, at = {}, 0
    for key, shape in CARRY.items():
        strides = tuple(int(8 * np.prod(shape[k + 1 :])) for k in range(len(shape)))
        spans[key] = (at, shape, strides)
        at += int(np.prod(shape))
    return spans, at


SPANS, CARRY_WIDTH = _layout()
_S = tuple(SPANS.values())  # as the kernels read it (numba takes a global tuple as a constant)
FEET_AT = SPANS["feet_started"][0]  # the planter's state


@njit(cache=True, error_model="numpy", inline="always")
def _view(carry, span):
    """(B, *shape) view of one entry of the packed carry (B, CARRY_WIDTH), C-contiguous."""
    at, shape, strides = span
    return np.lib.stride_tricks.as_strided(carry.ravel()[at:], (carry.shape[0],) + shape, (carry.strides[0],) + strides)


@njit(cache=True, error_model="numpy", inline="always")
def unpack(carry, x):
    """The `Session` (with the LTI states x) and `Feet` records of a packed carry: views."""
    session = Session(
        _view(carry, _S[0]), _view(carry, _S[1]), _view(carry, _S[2]), _view(carry, _S[3]), _view(carry, _S[4]),
        _view(carry, _S[5]), _view(carry, _S[6]), _view(carry, _S[7]), _view(carry, _S[8]), _view(carry, _S[9]), x,
    )  # fmt: skip
    feet = Feet(
        _view(carry, _S[10]), _view(carry, _S[11]), _view(carry, _S[12]), _view(carry, _S[13]),
        _view(carry, _S[14]), _view(carry, _S[15]), _view(carry, _S[16]), _view(carry, _S[17]),
    )  # fmt: skip
    return session, feet


class Systems(NamedTuple):
    """Every style's translator concatenated in style order (`x_off`, `row_off`), in group order."""

    x_off: np.ndarray  # (S + 1,) int64
    row_off: np.ndarray  # (S + 1,) int64
    indptr: np.ndarray  # (rows + 1,) int64, into indices/data, rows in group order
    indices: np.ndarray  # (nnz,) int32
    data: np.ndarray  # (nnz,)
    pos: np.ndarray  # (rows,) int64: where each row of M_s (row_off[s] + r) sits in the group order
    group_off: np.ndarray  # (S + 1,) int64: style s's groups, group_off[s]...
    groups: np.ndarray  # (G, 5) int64: a group's rows (first, end) in group order, its inputs (at, count) in `cols`, its block's start in `blocks`
    cols: np.ndarray  # (C,) int64: each group's inputs
    blocks: np.ndarray  # (sum of rows x inputs,) each group's [B; D] rows over its inputs, C order
    in_mean: np.ndarray  # (S, 67)
    in_std: np.ndarray  # (S, 67)
    in_lo: np.ndarray  # (S, 67) training range of the normalised input (erf blend)
    in_hi: np.ndarray  # (S, 67)
    out_mean: np.ndarray  # (S, 68)
    out_std: np.ndarray  # (S, 68)
    k: np.ndarray  # (S, 2) erf blend k_p, k_c
    ref: np.ndarray  # (S, 22, 4) per-joint reference rotations
    keep: float  # per frame, the share of the blend weight's eased history kept (`ease`)
    steady: np.ndarray  # (x_off[S], 67) rows x_off[s]:x_off[s+1]: style s's (I - A)^-1 B (`start_state`)


class Footplant(NamedTuple):
    """Each style's footplant classifier (`footplant.py`) on its LTI state."""

    w: np.ndarray  # (2, N) projection per foot, columns aligned with the state
    mean: np.ndarray  # (S, 2, 2) per foot, per class (free, planted)
    var: np.ndarray  # (S, 2, 2)
    log_prior: np.ndarray  # (S, 2, 2)
    fitted: np.ndarray  # (S,) bool
    log_var: np.ndarray  # (S, 2, 2) log(var), computed once (math.log, as the step did per frame)


class Ball(NamedTuple):
    """Each style's rotation prior (`train.style_prior`): per joint, mean rotation and radii."""

    mean: np.ndarray  # (S, 22, 4)
    radii: np.ndarray  # (S, 2, 22) inner, outer (radians; inf: no prior)
    cos_inner: np.ndarray  # (S, 22) cos(inner / 2), -1 without a prior: a rotation this close is left as it is


class Bends(NamedTuple):
    """Hinge joints held at no less than their least real bend (`models.motion.hinge.kernel_floor`)."""

    bone: np.ndarray  # (22, 3) each joint's bone axis
    hinge: np.ndarray  # (22, 3) its hinge axis (real bends positive)
    floor: np.ndarray  # (22,) its least real bend (radians; -inf: not held)


class RaisedArm(NamedTuple):
    """The styles' raised-arm carries (`raised_arm.py`), stacked; style s uses row[s] (-1: none)."""

    source: np.ndarray  # (C, J, 4)
    mean: np.ndarray  # (C, J, 4)
    map: np.ndarray  # (C, J, 3, 3)
    radius: np.ndarray  # (C, J)
    row: np.ndarray  # (S,) int64
    joints: np.ndarray  # (2, K) int64: each side's arm, Shoulder to Hand
    raise_ramp: np.ndarray  # (2,) cm: the hand's height over its shoulder, raise share 0 -> 1
    wave_ramp: np.ndarray  # (2,) cm/s: its sway, wave share 0 -> 1
    keep: float  # per frame, the share of the eased share's history kept (`raised_shares`)


class Switches(NamedTuple):
    """The stages after the translator, each on or off."""

    blend: bool  # toward the input outside the training range (erf)
    keep_heading: bool  # the output's yaw change is the input's
    raised_arm: bool
    footlock: bool
    saturate: bool  # the systems read the input saturated into its training range (`saturate`)
    foot_pitch: bool  # the feet's pitch against the ground partly the input's (`feet_kernels.follow_pitch`)


class Work(NamedTuple):
    """Scratch kept between steps (fresh buffers cost more in page faults than the arithmetic)."""

    session: np.ndarray  # (B, 18): yaw, yaw-free hips, root displacement and yaw change, the input's share, ...
    quats: np.ndarray  # (B, S, 22, 4) each style's body rotations
    rows: np.ndarray  # (B,) int64: the sessions using a style
    blend_w: np.ndarray  # (CHUNK,) of a chunk of the sessions using a style
    xin: np.ndarray  # flat: their x, (n, k)
    u: np.ndarray  # flat: their normalised features, (67, k)
    z: np.ndarray  # flat: M [x; u], (n + 67, k)
    feats: np.ndarray  # flat: their raw features, (67, k)
    out: np.ndarray  # flat: the output features of a chunk of the sessions using a style, (k, 67)
    root: np.ndarray  # (B, 3) the translated root, before the feet are planted
    contacts: np.ndarray  # (B, 2) bool: the footplant classifier's
    active: np.ndarray  # (B,) bool: a style weight > 0
    carry_w: np.ndarray  # (1, C) one session's raised-arm carry weights
    carried: np.ndarray  # (1, J, 4) its carried rotations
    point: np.ndarray  # (B, 2) int64: the planter's held points, as it indexes with them
    group_u: np.ndarray  # flat: the normalised features a group of rows reads, (inputs, k)
    styled_rotations: np.ndarray  # (B, J, 4) the body before the unseen-content fade (`step`)
    proj: np.ndarray  # flat: the footplant discriminants of a chunk of the sessions using a style, (2, k)


def new_work(batch: int, systems: Systems, carries: int) -> tuple[np.ndarray, ...]:
    """Scratch for steps of up to `batch` sessions of these styles, packed (`pack`)."""
    styles = len(systems.x_off) - 1
    n, k = int(np.diff(systems.x_off).max()), min(batch, CHUNK)
    work = Work(
        np.empty((batch, 18)),
        np.empty((batch, styles, NUM_JOINTS, 4)),
        np.empty(batch, np.int64),
        np.empty(k),
        np.empty(n * k),
        np.empty(FEATURE_DIM * k),
        np.empty((n + FEATURE_DIM) * k),
        np.empty(FEATURE_DIM * k),
        np.empty(k * FEATURE_DIM),
        np.empty((batch, 3)),
        np.empty((batch, 2), np.bool_),
        np.empty(batch, np.bool_),
        np.empty((1, carries)),
        np.empty((1, NUM_JOINTS, 4)),
        np.empty((batch, 2), np.int64),
        np.empty(FEATURE_DIM * k),
        np.empty((batch, NUM_JOINTS, 4)),
        np.empty(2 * k),
    )
    return pack([work], [WORK_SCHEMA], copy=False)


# --------------------------------------------------------------------------- records in flat buffers

# Each record's fields: f float64, i int64, b bool; 0 a scalar, else the number of dimensions.
CONSTANT_SCHEMAS = (
    "i1 i1 i1 i1 f1 i1 i1 i2 i1 f1 f2 f2 f2 f2 f2 f2 f2 f3 f0 f2",  # Systems
    "f2 f3 f3 f3 b1 f3",  # Footplant
    "f3 f3 f2",  # Ball
    "i1 f2 i1 i1 i1 f0 f0 f0",  # Hands
    "f3 f3 f4 f2 i1 i2 f1 f1 f0",  # RaisedArm
    "i0 i2 f2 f1 f0 f0 f0 f0 f0 f0 f0 f0 f0 f0 f0 f0",  # `FootPlanter`'s parameters (`plant_feet`'s last)
    "b0 b0 b0 b0 b0 b0",  # Switches
    "f2 f2 f1",  # Bends
)
WORK_SCHEMA = "f2 f4 i1 f1 f1 f1 f1 f1 f1 f2 b2 b1 f2 f3 i2 f1 f3 f1"


def pack(
    records: list[tuple], schemas: list[str], copy: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All fields of `records` in three buffers (float64, int64, bool) plus an index: four arrays to unbox."""
    kinds = [kind for schema in schemas for kind in schema.split()]
    fields = [np.asarray(v) for record in records for v in record]
    if len(fields) != len(kinds):
        raise ValueError(f"{len(fields)} fields for a schema of {len(kinds)}")
    dtypes = {"f": np.float64, "i": np.int64, "b": np.bool_}
    index = np.zeros((len(fields), 6), np.int64)
    sizes = {"f": 0, "i": 0, "b": 0}
    for k, (value, kind) in enumerate(zip(fields, kinds)):
        if value.ndim != int(kind[1]) or value.dtype.kind not in {"f": "f", "i": "iu", "b": "b"}[kind[0]]:
            raise ValueError(f"field {k}: {value.dtype}{value.shape} is not {kind}")
        index[k, :2] = sizes[kind[0]], value.size
        index[k, 2 : 2 + value.ndim] = value.shape
        sizes[kind[0]] += value.size
    flat: list[np.ndarray] = [np.empty(sizes[c], dtypes[c]) for c in "fib"]
    if copy:
        for value, kind, (at, size) in zip(fields, kinds, index[:, :2]):
            flat["fib".index(kind[0])][at : at + size] = value.ravel()
    return flat[0], flat[1], flat[2], index


@njit(cache=True, error_model="numpy", inline="always")
def _f(p, k):
    at = p[3][k, 0]
    return p[0][at : at + p[3][k, 1]]


@njit(cache=True, error_model="numpy", inline="always")
def _i(p, k):
    at = p[3][k, 0]
    return p[1][at : at + p[3][k, 1]]


@njit(cache=True, error_model="numpy", inline="always")
def _b(p, k):
    at = p[3][k, 0]
    return p[2][at : at + p[3][k, 1]]


@njit(cache=True, error_model="numpy", inline="always")
def _s2(p, k):
    return (p[3][k, 2], p[3][k, 3])


@njit(cache=True, error_model="numpy", inline="always")
def _s3(p, k):
    return (p[3][k, 2], p[3][k, 3], p[3][k, 4])


@njit(cache=True, error_model="numpy", inline="always")
def _s4(p, k):
    return (p[3][k, 2], p[3][k, 3], p[3][k, 4], p[3][k, 5])


@njit(cache=True, error_model="numpy", inline="always")
def unpack_constants(p):
    """The step's constant records from `pack` (`CONSTANT_SCHEMAS`' order), as views."""
    sys = Systems(
        _i(p, 0), _i(p, 1), _i(p, 2), _i(p, 3), _f(p, 4), _i(p, 5), _i(p, 6), _i(p, 7).reshape(_s2(p, 7)), _i(p, 8),
        _f(p, 9), _f(p, 10).reshape(_s2(p, 10)),
        _f(p, 11).reshape(_s2(p, 11)), _f(p, 12).reshape(_s2(p, 12)), _f(p, 13).reshape(_s2(p, 13)),
        _f(p, 14).reshape(_s2(p, 14)), _f(p, 15).reshape(_s2(p, 15)), _f(p, 16).reshape(_s2(p, 16)),
        _f(p, 17).reshape(_s3(p, 17)), _f(p, 18)[0], _f(p, 19).reshape(_s2(p, 19)),
    )  # fmt: skip
    fp = Footplant(
        _f(p, 20).reshape(_s2(p, 20)), _f(p, 21).reshape(_s3(p, 21)), _f(p, 22).reshape(_s3(p, 22)),
        _f(p, 23).reshape(_s3(p, 23)), _b(p, 24), _f(p, 25).reshape(_s3(p, 25)),
    )  # fmt: skip
    ball = Ball(_f(p, 26).reshape(_s3(p, 26)), _f(p, 27).reshape(_s3(p, 27)), _f(p, 28).reshape(_s2(p, 28)))
    hands = Hands(
        _i(p, 29), _f(p, 30).reshape(_s2(p, 30)), _i(p, 31), _i(p, 32), _i(p, 33), _f(p, 34)[0], _f(p, 35)[0],
        _f(p, 36)[0],
    )  # fmt: skip
    arm = RaisedArm(
        _f(p, 37).reshape(_s3(p, 37)), _f(p, 38).reshape(_s3(p, 38)), _f(p, 39).reshape(_s4(p, 39)),
        _f(p, 40).reshape(_s2(p, 40)), _i(p, 41), _i(p, 42).reshape(_s2(p, 42)), _f(p, 43), _f(p, 44),
        _f(p, 45)[0],
    )  # fmt: skip
    planter = (
        _i(p, 46)[0], _i(p, 47).reshape(_s2(p, 47)), _f(p, 48).reshape(_s2(p, 48)), _f(p, 49), _f(p, 50)[0],
        _f(p, 51)[0], _f(p, 52)[0], _f(p, 53)[0], _f(p, 54)[0], _f(p, 55)[0], _f(p, 56)[0], _f(p, 57)[0],
        _f(p, 58)[0], _f(p, 59)[0], _f(p, 60)[0], _f(p, 61)[0],
    )  # fmt: skip
    on = Switches(_b(p, 62)[0], _b(p, 63)[0], _b(p, 64)[0], _b(p, 65)[0], _b(p, 66)[0], _b(p, 67)[0])
    bends = Bends(_f(p, 68).reshape(_s2(p, 68)), _f(p, 69).reshape(_s2(p, 69)), _f(p, 70))
    return sys, fp, ball, hands, arm, planter, on, bends


@njit(cache=True, error_model="numpy", inline="always")
def unpack_work(p):
    """The `Work` record from `pack([work])`: views."""
    return Work(
        _f(p, 0).reshape(_s2(p, 0)), _f(p, 1).reshape(_s4(p, 1)), _i(p, 2), _f(p, 3), _f(p, 4), _f(p, 5), _f(p, 6),
        _f(p, 7), _f(p, 8), _f(p, 9).reshape(_s2(p, 9)), _b(p, 10).reshape(_s2(p, 10)), _b(p, 11),
        _f(p, 12).reshape(_s2(p, 12)), _f(p, 13).reshape(_s3(p, 13)), _i(p, 14).reshape(_s2(p, 14)), _f(p, 15),
        _f(p, 16).reshape(_s3(p, 16)), _f(p, 17),
    )  # fmt: skip


# --------------------------------------------------------------------------- small maths


@njit(cache=True, error_model="numpy")
def split_hips(q):
    """q_hips = qyaw(yaw) * tilt -> (yaw, tilt); see representation.split_hips."""
    x, y, z, w = q
    yaw = math.atan2(2.0 * (y * z + w * x), -2.0 * (x * y - w * z))
    c, s = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return yaw, (c * x - s * z, c * y - s * w, c * z + s * x, c * w + s * y)


@njit(cache=True, error_model="numpy")
def add_signed(acc, w, q, ref):
    """acc + w * q, with q's sign flipped when it points away from ref (q and -q are one rotation)."""
    sign = -w if qdot(q, ref) < 0.0 else w
    return (acc[0] + sign * q[0], acc[1] + sign * q[1], acc[2] + sign * q[2], acc[3] + sign * q[3])


# --------------------------------------------------------------------------- 1. the translator


@njit(cache=True, error_model="numpy")
def project(z, pos, fp, a, proj):
    """Each foot's footplant discriminant of the chunk's new states into proj (2, k)."""
    k = proj.shape[1]
    if k == 1:
        left, right = 0.0, 0.0
        for i in range(pos.shape[0]):
            state = z[pos[i], 0]
            left += state * fp.w[0, a + i]
            right += state * fp.w[1, a + i]
        proj[0, 0], proj[1, 0] = left, right
        return
    for c in range(k):
        proj[0, c], proj[1, c] = 0.0, 0.0
    for i in range(pos.shape[0]):
        row, left, right = pos[i], fp.w[0, a + i], fp.w[1, a + i]
        for c in range(k):
            proj[0, c] += z[row, c] * left
            proj[1, c] += z[row, c] * right


@njit(cache=True, error_model="numpy")
def _likelier(proj, fp, s, foot):
    """Whether planted is the likelier Gaussian class of style s's discriminant."""
    mean, var, log_prior = fp.mean[s, foot], fp.var[s, foot], fp.log_prior[s, foot]
    log_var = fp.log_var[s, foot]
    ll_free = -0.5 * (proj - mean[0]) ** 2 / var[0] - 0.5 * log_var[0] + log_prior[0]
    ll_planted = -0.5 * (proj - mean[1]) ** 2 / var[1] - 0.5 * log_var[1] + log_prior[1]
    return ll_planted > ll_free


@njit(cache=True, error_model="numpy")
def style_inputs(sys, s, root_y, rotations, tilt, delta, x, xin, feats, c):
    """One session's state and raw features (`representation`) for style s into column c."""
    feats[0, c], feats[1, c], feats[2, c], feats[3, c] = delta[0], delta[1], delta[2], root_y
    for j in range(1, NUM_JOINTS):
        q = tilt if j == HIPS else row4(rotations, j)
        r = qlog(qmul(qinv(quat_at(sys.ref, s, j)), q))
        feats[3 * j + 1, c], feats[3 * j + 2, c], feats[3 * j + 3, c] = r
    for i in range(x.shape[0]):
        xin[i, c] = x[i]


@njit(cache=True, error_model="numpy")
def normalise(sys, s, feats, u, blend, raw):
    """Style s's normalised features into u, each session's erf blend weight into raw."""
    k = raw.shape[0]
    if k == 1:
        top = 0.0
        for d in range(FEATURE_DIM):
            ud = (feats[d, 0] - sys.in_mean[s, d]) / sys.in_std[s, d]
            u[d, 0] = ud
            beyond = max(ud - sys.in_hi[s, d], sys.in_lo[s, d] - ud) - sys.k[s, 0]
            if blend and beyond > top:
                top = beyond
        raw[0] = math.erf(top / sys.k[s, 1]) if top > 0.0 else 0.0
        return
    for c in range(k):
        raw[c] = 0.0  # first the largest distance past k_p
    for d in range(FEATURE_DIM):
        mean, std = sys.in_mean[s, d], sys.in_std[s, d]
        for c in range(k):
            u[d, c] = (feats[d, c] - mean) / std
        if blend:
            hi, lo, k_p = sys.in_hi[s, d], sys.in_lo[s, d], sys.k[s, 0]
            for c in range(k):
                beyond = max(u[d, c] - hi, lo - u[d, c]) - k_p
                if beyond > raw[c]:
                    raw[c] = beyond
    for c in range(k):  # erf(0) = 0 inside the training range: most sessions, most frames
        raw[c] = math.erf(raw[c] / sys.k[s, 1]) if raw[c] > 0.0 else 0.0


@njit(cache=True, error_model="numpy")
def saturate(sys, s, u):
    """u saturated into style s's training range (hi + k_p tanh((u - hi) / k_p)): the systems never
    extrapolate, only the excess passes through (the erf blend hands back the whole body)."""
    k_p = sys.k[s, 0]
    for d in range(FEATURE_DIM):
        hi, lo = sys.in_hi[s, d], sys.in_lo[s, d]
        for c in range(u.shape[1]):
            x = u[d, c]
            if x > hi:
                u[d, c] = hi + k_p * math.tanh((x - hi) / k_p)
            elif x < lo:
                u[d, c] = lo - k_p * math.tanh((lo - x) / k_p)


@njit(cache=True, error_model="numpy")
def unset(x):
    """Whether a style's state is exactly zero: unset (a running system's state never is)."""
    for i in range(x.shape[0]):
        if x[i] != 0.0:
            return False
    return True


@njit(cache=True, error_model="numpy")
def start_state(sys, s, u, xin, c):
    """Column c of xin := style s's steady state on u held constant: where a session starts."""
    gain = sys.steady[sys.x_off[s] : sys.x_off[s + 1]]
    for i in range(gain.shape[0]):
        acc = 0.0
        for d in range(FEATURE_DIM):
            acc += gain[i, d] * u[d, c]
        xin[i, c] = acc


@njit(cache=True, error_model="numpy")
def ease(raw, history, keep):
    """A weight eased by two one-pole followers in series, keeping `keep` per frame; history (set, fast,
    slow); returns (fast, slow), the slow one applied: a jumping weight would spike acceleration."""
    fast, slow = (history[1], history[2]) if history[0] != 0.0 else (raw, raw)
    fast = keep * fast + (1.0 - keep) * raw
    return fast, keep * slow + (1.0 - keep) * fast


def eased(raw: np.ndarray, keep: float) -> np.ndarray:
    """(F,) `ease` over a whole sequence, for the offline path."""
    out = np.empty(len(raw))
    history = (0.0, 0.0, 0.0)
    for t, r in enumerate(raw):
        fast, out[t] = ease(float(r), history, keep)
        history = (1.0, fast, out[t])
    return out


@njit(cache=True, error_model="numpy")
def system_product(sys, s, xin, u, z, group_u):
    """z = M_s [xin; u] (rows in group order): dense [B; D] blocks, then the sparse [A; C] xin."""
    r0, m = sys.row_off[s], xin.shape[1]
    for g in range(sys.group_off[s], sys.group_off[s + 1]):
        first, end, at, count, block = sys.groups[g]
        rows = z[first:end]
        if count == 0:  # rows that read no input
            rows[:] = 0.0
            continue
        ug = group_u[: count * m].reshape((count, m))
        for i in range(count):
            for c in range(m):
                ug[i, c] = u[sys.cols[at + i], c]
        weights = sys.blocks[block : block + (end - first) * count].reshape((end - first, count))
        if m == 1:
            np.dot(weights, ug.reshape(count), rows.reshape(end - first))
        else:
            np.dot(weights, ug, rows)
    for r in range(z.shape[0]):
        first, end = sys.indptr[r0 + r], sys.indptr[r0 + r + 1]
        if m == 1:
            acc = z[r, 0]
            for p in range(first, end):
                acc += sys.data[p] * xin[sys.indices[p], 0]
            z[r, 0] = acc
            continue
        # two entries a pass: half the stores to z (which can alias the loads modulo 4 kB)
        row = z[r]
        for p in range(first, end - 1, 2):
            a, states_a = sys.data[p], xin[sys.indices[p]]
            b, states_b = sys.data[p + 1], xin[sys.indices[p + 1]]
            for c in range(m):
                row[c] += a * states_a[c] + b * states_b[c]
        if (end - first) % 2:
            a, states_a = sys.data[end - 1], xin[sys.indices[end - 1]]
            for c in range(m):
                row[c] += a * states_a[c]


@njit(cache=True, error_model="numpy")
def inside(q, mean, cos_inner):
    """Whether unit q is within the inner radius of `mean` (cos(angle / 2) >= cos(inner / 2))."""
    return abs(qdot(mean, q)) >= cos_inner


@njit(cache=True, error_model="numpy")
def chunk_outputs(sys, s, z, feats, u, blend_w, keep_heading, rows, x, a, out):
    """Style s's new states of a chunk's sessions (`rows`) into x's columns a..., and each one's
    output features into out (k, 67). Row by row of z: a session's column of z lies k * 8 bytes
    apart, and gathered one session at a time every entry missed the cache (~1 us a session)."""
    pos = sys.pos[sys.row_off[s] : sys.row_off[s + 1]]
    n, k = sys.x_off[s + 1] - sys.x_off[s], blend_w.shape[0]
    for i in range(n):
        r = pos[i]
        for c in range(k):
            x[rows[c], a + i] = z[r, c]
    for d in range(FEATURE_DIM):  # the log time warp (last output) is not used online
        r, in_mean, in_std = pos[n + d], sys.in_mean[s, d], sys.in_std[s, d]
        out_mean, out_std = sys.out_mean[s, d], sys.out_std[s, d]
        for c in range(k):
            excess = feats[d, c] - (u[d, c] * in_std + in_mean)  # the input's excess past its range
            y = z[r, c] * out_std + out_mean + excess
            out[c, d] = (1.0 - blend_w[c]) * y + blend_w[c] * feats[d, c]
    if keep_heading:
        for c in range(k):
            out[c, 2] = feats[2, c]


@njit(cache=True, error_model="numpy")
def style_outputs(sys, ball, bends, s, w, out, root_feats, quats):
    """Style s's rotations for one session from its output features `out` (67,), held in the
    style's ball and on its hinges; its root features added at weight w."""
    for d in range(4):
        root_feats[d] += w * out[d]
    # body rotations (`tests/reference/lti_offline.static_to_rotations` with yaw 0)
    quats[0, 0], quats[0, 1], quats[0, 2], quats[0, 3] = 0.0, 0.0, 0.0, 1.0
    for j in range(1, NUM_JOINTS):
        q = qmul(quat_at(sys.ref, s, j), qexp((out[3 * j + 1], out[3 * j + 2], out[3 * j + 3])))
        if j == HIPS or not inside(q, quat_at(ball.mean, s, j), ball.cos_inner[s, j]):
            q = clamp_joint(q, quat_at(ball.mean, s, j), ball.radii[s, 0, j], ball.radii[s, 1, j], j == HIPS)
        if bends.floor[j] > -math.inf:
            q = floor_bend(q, row3(bends.bone, j), row3(bends.hinge, j), bends.floor[j])
        quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3] = q


@njit(cache=True, error_model="numpy")
def translate(frame, before, after, sys, fp, ball, bends, switches, work, out_rot):
    """The published translator (model.LTIStyleModel): input roots per session, LTI steps per style, blends."""
    B, S = frame.weights.shape
    weights, per = frame.weights, work.session
    yaws, tilts, deltas, rests = per[:, 0], per[:, 1:5], per[:, 5:8], per[:, 8]
    totals, root_feats, votes, eased = per[:, 9], per[:, 10:14], per[:, 14:16], per[:, 16:18]
    for b in range(B):
        for i in range(after.x.shape[1]):
            after.x[b, i] = 0.0  # a style at weight 0 rests at x = 0, unset (`unset`, `start_state`)
        work.contacts[b, 0], work.contacts[b, 1] = False, False
        yaw, tilt = split_hips(quat_at(frame.rotations, b, HIPS))
        yaws[b], votes[b, 0], votes[b, 1], eased[b, 0], eased[b, 1] = yaw, 0.0, 0.0, 0.0, 0.0
        tilts[b, 0], tilts[b, 1], tilts[b, 2], tilts[b, 3] = tilt
        gx, gz = frame.root[b, 0], frame.root[b, 2]
        started = before.started[b]
        p_yaw = before.in_yaw[b] if started else yaw
        p_x = before.in_ground[b, 0] if started else gx
        p_z = before.in_ground[b, 1] if started else gz
        dx, dz = turn_y(gx - p_x, gz - p_z, math.cos(-p_yaw), math.sin(-p_yaw))
        deltas[b, 0], deltas[b, 1], deltas[b, 2] = dx, dz, wrap(yaw - p_yaw)
        total = 0.0
        for s in range(S):
            total += weights[b, s]
        totals[b] = total
        rests[b] = max(1.0 - total, 0.0)  # share of the input passing through
        for d in range(3):
            root_feats[b, d] = rests[b] * deltas[b, d]
        root_feats[b, 3] = rests[b] * frame.root[b, 1]
    for s in range(S):
        m = 0
        for b in range(B):
            if weights[b, s] > 0.0:
                work.rows[m] = b
                m += 1
        if m == 0:
            continue
        a = frame.x_at[s]
        e = a + sys.x_off[s + 1] - sys.x_off[s]
        for lo in range(0, m, CHUNK):  # a few sessions at a time: their columns stay in cache
            k = min(CHUNK, m - lo)
            xin = work.xin[: (e - a) * k].reshape((e - a, k))
            u = work.u[: FEATURE_DIM * k].reshape((FEATURE_DIM, k))
            z = work.z[: (e - a + FEATURE_DIM) * k].reshape((e - a + FEATURE_DIM, k))
            feats = work.feats[: FEATURE_DIM * k].reshape((FEATURE_DIM, k))
            for c in range(k):
                b = work.rows[lo + c]
                style_inputs(
                    sys, s, frame.root[b, 1], frame.rotations[b], row4(tilts, b), deltas[b], before.x[b, a:e], xin,
                    feats, c,
                )  # fmt: skip
            normalise(sys, s, feats, u, switches.blend, work.blend_w[:k])
            if switches.saturate:
                saturate(sys, s, u)
            for c in range(k):
                if unset(before.x[work.rows[lo + c], a:e]):
                    start_state(sys, s, u, xin, c)
            for c in range(k):
                b = work.rows[lo + c]
                # each style eases its own weight from the session's shared history
                fast, work.blend_w[c] = ease(work.blend_w[c], before.blend[b], sys.keep)
                eased[b, 0] += weights[b, s] * fast
                eased[b, 1] += weights[b, s] * work.blend_w[c]
            system_product(sys, s, xin, u, z, work.group_u)
            proj = work.proj[: 2 * k].reshape((2, k))
            if fp.fitted[s]:
                project(z, sys.pos[sys.row_off[s] : sys.row_off[s] + e - a], fp, sys.x_off[s], proj)
            outs = work.out[: k * FEATURE_DIM].reshape((k, FEATURE_DIM))
            chunk_outputs(
                sys, s, z, feats, u, work.blend_w[:k], switches.keep_heading, work.rows[lo:], after.x, a, outs
            )
            for c in range(k):
                b = work.rows[lo + c]
                w = weights[b, s]
                style_outputs(sys, ball, bends, s, w, outs[c], root_feats[b], work.quats[b, s])
                if fp.fitted[s]:
                    votes[b, 0] += w * _likelier(proj[0, c], fp, s, 0)
                    votes[b, 1] += w * _likelier(proj[1, c], fp, s, 1)
    for b in range(B):
        fresh = not before.started[b]
        yaw, rest, rf, quats = yaws[b], rests[b], root_feats[b], work.quats[b]
        base, base_w = -1, rest  # the heaviest part (first on ties): the sign reference of the blend
        for s in range(S):
            if weights[b, s] > base_w:
                base, base_w = s, weights[b, s]
        # blend the body: input (with the yaw-free hips) and each style, signs aligned to the base part
        out_rot[b, 0, 0], out_rot[b, 0, 1], out_rot[b, 0, 2], out_rot[b, 0, 3] = 0.0, 0.0, 0.0, 1.0
        for j in range(1, NUM_JOINTS):
            q_in = row4(tilts, b) if j == HIPS else quat_at(frame.rotations, b, j)
            q_base = q_in if base < 0 else quat_at(quats, base, j)
            acc = (0.0, 0.0, 0.0, 0.0)
            if rest > 0.0:
                acc = add_signed(acc, rest, q_in, q_base)
            for s in range(S):
                if weights[b, s] > 0.0:
                    acc = add_signed(acc, weights[b, s], quat_at(quats, s, j), q_base)
            q = qunit(acc)
            if j == HIPS:
                q = qmul(qyaw(yaw if fresh else before.out_yaw[b] + rf[2]), q)
            out_rot[b, j, 0], out_rot[b, j, 1], out_rot[b, j, 2], out_rot[b, j, 3] = q
        # integrate the output path: the first frame starts where the input is
        gx, gz = frame.root[b, 0], frame.root[b, 2]
        if fresh:
            after.out_yaw[b], after.out_ground[b, 0], after.out_ground[b, 1] = yaw, gx, gz
        else:
            sx, sz = turn_y(rf[0], rf[1], math.cos(before.out_yaw[b]), math.sin(before.out_yaw[b]))
            after.out_yaw[b] = before.out_yaw[b] + rf[2]
            after.out_ground[b, 0] = before.out_ground[b, 0] + sx
            after.out_ground[b, 1] = before.out_ground[b, 1] + sz
        work.root[b, 0], work.root[b, 1], work.root[b, 2] = after.out_ground[b, 0], rf[3], after.out_ground[b, 1]
        after.started[b] = True
        after.in_yaw[b], after.in_ground[b, 0], after.in_ground[b, 1] = yaw, gx, gz
        after.blend[b, 0], after.blend[b, 1], after.blend[b, 2] = 0.0, 0.0, 0.0  # no style: starts again
        if totals[b] > 0.0:
            after.blend[b, 0], after.blend[b, 1], after.blend[b, 2] = (
                1.0,
                eased[b, 0] / totals[b],
                eased[b, 1] / totals[b],
            )
            limit = 0.5 * max(totals[b], 1e-12)
            work.contacts[b, 0], work.contacts[b, 1] = votes[b, 0] > limit, votes[b, 1] > limit


# --------------------------------------------------------------------------- 3. the raised arm


@njit(cache=True, error_model="numpy", inline="always")
def ramp(x, lo, hi):
    """0 up to lo, 1 from hi, linear between (`models.motion.hands` shares)."""
    return min(max((x - lo) / (hi - lo), 0.0), 1.0)


@njit(cache=True, error_model="numpy")
def calm_share(arm, height, sway):
    """How far a hand is raised and calm: its raise share times one minus its wave share."""
    return ramp(height, arm.raise_ramp[0], arm.raise_ramp[1]) * (1.0 - ramp(sway, arm.wave_ramp[0], arm.wave_ramp[1]))


@njit(cache=True, error_model="numpy")
def raised_shares(b, arm, on, raised, weights, offsets, swayed, fresh, before, after):
    """Session b's eased share of each side's raised arm; 0 below `SHARE_FLOOR`."""
    carried = False
    if on and raised:
        for s in range(weights.shape[1]):
            carried = carried or (arm.row[s] >= 0 and weights[b, s] > 0.0)
    for side in range(2):
        raw = calm_share(arm, offsets[b, side, 1], swayed[b, side]) if carried else 0.0
        after[side, 0], after[side, 1] = ease(raw, (0.0 if fresh else 1.0, before[side, 0], before[side, 1]), arm.keep)
    left, right = after[0, 1], after[1, 1]
    return (left if left >= SHARE_FLOOR else 0.0), (right if right >= SHARE_FLOOR else 0.0)


@njit(cache=True, error_model="numpy")
def carry_raised_arms(b, arm, weights, left, right, out_rot, work):
    """Session b's arms mixed toward the styles' raised arms, each side by its share."""
    total = 0.0
    for s in range(weights.shape[1]):
        k = arm.row[s]
        if k >= 0:
            work.carry_w[0, k] = weights[b, s]
            total += weights[b, s]
    if not total > 0.0:
        return
    carry_batch(out_rot[b : b + 1], work.carry_w, arm.source, arm.mean, arm.map, arm.radius, HIPS, work.carried)
    for side in range(2):
        share = left if side == 0 else right
        if not share > 0.0:
            continue
        for j in arm.joints[side]:
            q = nlerp(quat_at(out_rot, b, j), quat_at(work.carried, 0, j), share)
            out_rot[b, j, 0], out_rot[b, j, 1], out_rot[b, j, 2], out_rot[b, j, 3] = q


# --------------------------------------------------------------------------- the step


@njit(cache=True, error_model="numpy")
def step(frame, x, new_x, carry, new_carry, out, constants, work, fade):
    """One frame for every session; `constants` and `work` packed (`pack`). `fade`: the
    unseen-content fade's arrays (`novelty_kernels.fade_step`), applied before the feet are
    planted, or with no state rows (`model.NO_FADE`): none. One kernel for both, as each compiled
    variant of the step costs ~30 s of a core."""
    frame, out, work, constants = Frame(*frame), Output(*out), unpack_work(work), unpack_constants(constants)
    (before, feet_before), (after, feet_after) = unpack(carry, x), unpack(new_carry, new_x)
    styled = Output(out.root, work.styled_rotations, out.contacts)  # `style` leaves its root alone
    style(frame, before, after, styled, constants, work)
    control, old, reference, new, faded = fade
    if new.shape[0] == 0:
        out.rotations[:] = styled.rotations
    else:
        inputs = (frame.rotations, frame.root, styled.rotations, work.root, control, old, reference)
        fade_step(*inputs, out.rotations, out.root, new, faded)
        work.root[:] = out.root
    plant(frame, feet_before, feet_after, carry, new_carry, out, constants, work)


@njit(cache=True, error_model="numpy", inline="always")
def style(frame, before, after, out, constants, work):
    """`step`'s stages up to the feet."""
    sys, fp, ball, hands, arm, planter, on, bends = constants
    B = frame.root.shape[0]

    # 1. the translator
    translate(frame, before, after, sys, fp, ball, bends, on, work, out.rotations)

    # 2. the input's hands: how high, how they sway and rise
    hand_step(
        frame.rotations, hands, before.hand_prev, before.hand_sway, before.hand_rise, before.started,
        after.hand_prev, after.hand_sway, after.hand_rise,
    )  # fmt: skip

    # 3. the arms of raised hands that hold still, carried
    for b in range(B):
        raised = False
        for side in range(2):
            raised = raised or after.hand_prev[b, side, 1] > hands.above
        left, right = raised_shares(
            b, arm, on.raised_arm, raised, frame.weights, after.hand_prev, after.hand_sway, not before.started[b],
            before.raise_share[b], after.raise_share[b],
        )  # fmt: skip
        if left > 0.0 or right > 0.0:
            carry_raised_arms(b, arm, frame.weights, left, right, out.rotations, work)


@njit(cache=True, error_model="numpy", inline="always")
def plant(frame, feet_before, feet_after, carry, new_carry, out, constants, work):
    """`step`'s last stages: the feet's pitch, then the feet planted (`models.motion.feet`), the
    classifier's contacts as hints."""
    _, _, _, _, _, planter, on, _ = constants
    B = frame.root.shape[0]
    if on.foot_pitch:
        follow_pitch(frame.rotations, out.rotations, work.root, feet_before, planter, PITCH_SHARE)
    if not on.footlock:  # the planter's state waits
        new_carry[:, FEET_AT:] = carry[:, FEET_AT:]
        out.root[:] = work.root
        out.contacts[:] = work.contacts
        return
    for b in range(B):
        total = 0.0
        for s in range(frame.weights.shape[1]):
            total += frame.weights[b, s]
        work.active[b] = total > 0.0
        feet_after.started[b] = 1.0
        for leg in range(2):
            work.point[b, leg] = int(feet_before.point[b, leg])
    feet_after.model_root[:] = work.root  # the root it plants on (translated, faded), which it remembers
    # the planter indexes with its held points: the integer copy, not the carry's float view
    before = Feet(
        feet_before.started, feet_before.root, feet_before.model_root, feet_before.rel, feet_before.contact,
        work.point, feet_before.offset, feet_before.floor,
    )  # fmt: skip
    plant_feet(work.root, out.rotations, work.active, work.contacts, before, feet_after, out.rotations, planter)
    out.root[:] = feet_after.root
    for b in range(B):
        for leg in range(2):
            out.contacts[b, leg] = feet_after.contact[b, leg] != 0.0


# --------------------------------------------------------------------------- packing


def input_groups(inputs: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """Rows of [B; D] grouped by the inputs they read: (row order, per group (first, end, inputs))."""
    reads = inputs != 0.0
    keys: dict[bytes, list[int]] = {}
    for r, row in enumerate(reads):
        keys.setdefault(np.packbits(row).tobytes(), []).append(r)
    full = np.ones(inputs.shape[1], bool)
    merged: dict[bytes, list[int]] = {}
    for key, rows in keys.items():
        read = reads[rows[0]]
        saving = len(rows) * (inputs.shape[1] - read.sum())
        if read.any() and saving < GROUP_MIN_SAVING:
            key, read = np.packbits(full).tobytes(), full
        merged.setdefault(key, []).extend(rows)
    order: list[int] = []
    spans = []
    for key, rows in merged.items():
        read = np.flatnonzero(np.unpackbits(np.frombuffer(key, np.uint8))[: inputs.shape[1]])
        spans.append((len(order), len(order) + len(rows), read))
        order += sorted(rows)
    return np.array(order, np.int64), spans


def pack_styles(translators: list, keep: float) -> tuple[Systems, Footplant, Ball]:
    """The records of `StyleTranslator`s, blend weights eased by `keep`; once per style-set change."""
    from scipy import sparse

    x_off, row_off, indptr, indices, data = [0], [0], [], [], []
    pos, group_off, groups = [], [0], []
    cols: list[np.ndarray] = []
    blocks: list[np.ndarray] = []
    fp_w, fp_mean, fp_var, fp_prior, fitted, ball_mean, ball_radii = [], [], [], [], [], [], []
    nnz = 0
    for tr in translators:
        M = tr.M[: tr.n + FEATURE_DIM]  # not the log time warp, which is not used online
        order, spans = input_groups(M[:, tr.n :])
        M = M[order]
        states = sparse.csr_matrix(M[:, : tr.n])
        indptr.append(states.indptr[:-1] + nnz)
        indices.append(states.indices)
        data.append(states.data)
        nnz += states.nnz
        pos.append(np.argsort(order))
        for first, end, read in spans:
            groups.append((first, end, sum(len(c) for c in cols), len(read), sum(len(b) for b in blocks)))
            cols.append(read)
            blocks.append(M[first:end, tr.n + read].ravel())
        group_off.append(len(groups))
        x_off.append(x_off[-1] + tr.n)
        row_off.append(row_off[-1] + M.shape[0])
        f = tr.footplant
        fitted.append(f is not None)
        fp_w.append(f.w if f is not None else np.zeros((tr.n, 2)))
        fp_mean.append(f.mean if f is not None else np.zeros((2, 2)))
        fp_var.append(f.var if f is not None else np.ones((2, 2)))
        fp_prior.append(f.log_prior if f is not None else np.zeros((2, 2)))
        mean, radii = tr.ball()
        ball_mean.append(mean)
        ball_radii.append(radii)
    indptr.append(np.array([nnz]))
    f64 = lambda parts: np.ascontiguousarray(np.stack(parts), dtype=np.float64)  # noqa: E731
    systems = Systems(
        np.array(x_off, np.int64),
        np.array(row_off, np.int64),
        np.concatenate(indptr).astype(np.int64),
        np.concatenate(indices).astype(np.int32),
        np.concatenate(data).astype(np.float64),
        np.concatenate(pos).astype(np.int64),
        np.array(group_off, np.int64),
        np.array(groups, np.int64).reshape(-1, 5),
        np.concatenate(cols).astype(np.int64),
        np.concatenate(blocks).astype(np.float64),
        f64([tr.in_mean for tr in translators]),
        f64([tr.in_std for tr in translators]),
        f64([tr.in_lo for tr in translators]),
        f64([tr.in_hi for tr in translators]),
        f64([tr.out_mean for tr in translators]),
        f64([tr.out_std for tr in translators]),
        f64([(tr.k_p, tr.k_c) for tr in translators]),
        f64([tr.ref for tr in translators]),
        float(keep),
        np.ascontiguousarray(np.concatenate([tr.steady_gain() for tr in translators]), dtype=np.float64),
    )
    footplant = Footplant(
        np.ascontiguousarray(np.concatenate(fp_w).T, dtype=np.float64),
        f64(fp_mean),
        f64(fp_var),
        f64(fp_prior),
        np.array(fitted, np.bool_),
        f64([[[math.log(v) for v in foot] for foot in var] for var in fp_var]),
    )
    radii = f64(ball_radii)
    cos_inner = np.where(np.isfinite(radii[:, 0]), np.cos(0.5 * np.minimum(radii[:, 0], np.pi)), -1.0)
    return systems, footplant, Ball(f64(ball_mean), radii, np.ascontiguousarray(cos_inner))
