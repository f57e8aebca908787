"""`style_carry.StyleCarry` compiled (numba) for the per-frame step: the numpy reference's formulas
(`tests/reference/erd_carry.py`) as per-row, per-joint loops on 4-tuple quaternions, ~1 us per
session instead of ~40 small numpy calls. `_toward` and `_carry_joint` are inlined: out of line,
passing their arrays as numba structs cost a quarter to a half of the kernel's time.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from .quaternion import qdot, qexp, qinv, qlog, qmul, qneg, qscale, quat_at, qunit


@njit(cache=True, error_model="numpy")
def _mat3(m, s, j, v):
    """m[s, j] (3, 3) times the vector part of v."""
    return (
        m[s, j, 0, 0] * v[0] + m[s, j, 0, 1] * v[1] + m[s, j, 0, 2] * v[2],
        m[s, j, 1, 0] * v[0] + m[s, j, 1, 1] * v[1] + m[s, j, 1, 2] * v[2],
        m[s, j, 2, 0] * v[0] + m[s, j, 2, 1] * v[1] + m[s, j, 2, 2] * v[2],
    )


@njit(cache=True, error_model="numpy", inline="always")
def _toward(q, s, j, carry):
    """f_s(q) = mean exp(clamp(M log(src^-1 q))) for joint j and style s of `carry`."""
    source, mean, lin, radius = carry
    dx, dy, dz = _mat3(lin, s, j, qlog(qmul(qinv(quat_at(source, s, j)), q)))
    dn = math.sqrt(dx * dx + dy * dy + dz * dz)
    r = radius[s, j]
    if dn > r:
        k = r / dn
        dx, dy, dz = k * dx, k * dy, k * dz
    return qmul(quat_at(mean, s, j), qexp((dx, dy, dz)))


@njit(cache=True, error_model="numpy")
def _lone(w, b):
    """Row b's one style at weight 1 if that is all it has (no mix, no intensity), else < 0."""
    lone = -1
    for s in range(w.shape[1]):
        if w[b, s] != 0.0:
            lone = s if lone == -1 and w[b, s] == 1.0 else -2
    return lone


@njit(cache=True, error_model="numpy", inline="always")
def _headless(q, is_hips):
    """Unit q without its heading when it is the Hips: (q', heading), qmul(heading, q') = q."""
    hy, hw = 0.0, 1.0
    if is_hips:
        hn = math.sqrt(q[1] * q[1] + q[3] * q[3])
        if hn > 1e-9:
            hy, hw = q[1] / hn, q[3] / hn
        q = qmul((0.0, -hy, 0.0, hw), q)
    return q, (0.0, hy, 0.0, hw)


@njit(cache=True, error_model="numpy")
def _same_side(q, o):
    """o in q's hemisphere (the same rotation): a stream's quaternions never flip sign."""
    return qneg(o) if qdot(o, q) < 0.0 else o


@njit(cache=True, error_model="numpy", inline="always")
def _carry_joint(q, b, j, w, lone, carry):
    """Unit quaternion q of row b, joint j carried toward the styles of w[b] (`carry_batch`)."""
    if lone >= 0:
        return _same_side(q, _toward(q, lone, j, carry))
    cx = cy = cz = 0.0
    for s in range(w.shape[1]):
        ws = w[b, s]
        if ws == 0.0:
            continue
        lx, ly, lz = qlog(qmul(qinv(q), _toward(q, s, j, carry)))  # weighted
        cx += ws * lx
        cy += ws * ly
        cz += ws * lz
    return qmul(q, qexp((cx, cy, cz)))


@njit(cache=True, error_model="numpy")
def carry_batch(q, w, source, mean, lin, radius, hips, out):
    """out (B, J, 4) = q carried toward the styles of weights w (B, S), joint `hips` without its heading;
    one style at weight 1 takes f_s(q) itself (the same rotation at half the cost)."""
    for b in range(q.shape[0]):
        lone = _lone(w, b)
        for j in range(q.shape[1]):
            u, heading = _headless(qunit(quat_at(q, b, j)), j == hips)
            o = _carry_joint(u, b, j, w, lone, (source, mean, lin, radius))
            out[b, j, 0], out[b, j, 1], out[b, j, 2], out[b, j, 3] = qmul(heading, o) if j == hips else o
    return out


def carry(q: np.ndarray, w: np.ndarray, source, mean, lin, radius, hips: int = -1) -> np.ndarray:
    """`carry_batch` on any (B, J, 4) rotations and (B, S) weights."""
    q = np.ascontiguousarray(q, np.float64)
    out = np.empty_like(q)
    return carry_batch(q, np.ascontiguousarray(w, np.float64), source, mean, lin, radius, hips, out)


@njit(cache=True, error_model="numpy", inline="always")
def _kept(q, s, j, clamp, cos_half):
    """q kept in the range of `clamp` (a clamp alone: `StyleCarry.bounds`) for style s, joint j;
    q itself where already inside, so only a frame past the edge pays the log/exp round trip."""
    if abs(qdot(quat_at(clamp[1], s, j), q)) >= cos_half[s, j]:
        return q
    return _toward(q, s, j, clamp)


@njit(cache=True, error_model="numpy", inline="always")
def _pair_joint(q, row, j, w, lone, r, a, b, c, cos_c):
    """q of row `row`, joint j carried by `a` and by `b` then the clamp `c` (`cos_c`: its
    `_cos_half`), mixed by share r."""
    if r == 0.0:
        return _carry_joint(q, row, j, w, lone, a)
    if lone >= 0 and r == 1.0:
        return _same_side(q, _kept(_toward(q, lone, j, b), lone, j, c, cos_c))
    cx = cy = cz = 0.0
    for s in range(w.shape[1]):
        ws = w[row, s]
        if ws == 0.0:
            continue
        if r < 1.0:
            lx, ly, lz = qlog(qmul(qinv(q), _toward(q, s, j, a)))
            k = ws * (1.0 - r)
            cx, cy, cz = cx + k * lx, cy + k * ly, cz + k * lz
        lx, ly, lz = qlog(qmul(qinv(q), _kept(_toward(q, s, j, b), s, j, c, cos_c)))
        k = ws * r
        cx, cy, cz = cx + k * lx, cy + k * ly, cz + k * lz
    return qmul(q, qexp((cx, cy, cz)))


@njit(cache=True, error_model="numpy")
def carry_pair_batch(q, w, share, a, b, c, hips, out):
    """out: rotations carried toward the styles of w by `a` and by `b` then `c`, mixed by share r:

    q exp(sum_s w_s [(1 - r) log(q^-1 a_s(q)) + r log(q^-1 c_s(b_s(q)))]), `c` a clamp alone"""
    cos_c = _cos_half(c[3])
    for row in range(q.shape[0]):
        lone = _lone(w, row)
        for j in range(q.shape[1]):
            u, heading = _headless(qunit(quat_at(q, row, j)), j == hips)
            o = _pair_joint(u, row, j, w, lone, share[row], a, b, c, cos_c)
            out[row, j, 0], out[row, j, 1], out[row, j, 2], out[row, j, 3] = qmul(heading, o) if j == hips else o
    return out


def carry_pair(
    q: np.ndarray, w: np.ndarray, share: np.ndarray, a: tuple, b: tuple, c: tuple, hips: int = -1
) -> np.ndarray:
    """`carry_pair_batch` on any rotations; a, b, c: (source, mean, lin, radius) of each carry."""
    q = np.ascontiguousarray(q, np.float64)
    out = np.empty_like(q)
    w, share = np.ascontiguousarray(w, np.float64), np.ascontiguousarray(share, np.float64)
    return carry_pair_batch(q, w, share, a, b, c, hips, out)


@njit(cache=True, error_model="numpy")
def _paired(q, row, j, w, lone, r, a, b, c, cos_c):
    """`_pair_joint` out of line: inlined beside the plain carry it halved the speed of every row."""
    return _pair_joint(q, row, j, w, lone, r, a, b, c, cos_c)


@njit(cache=True, error_model="numpy")
def _clamped(q, row, j, w, lone, clamp):
    """q kept in the range of `clamp`; out of line (most joints skip it) to keep the loop small."""
    return _carry_joint(q, row, j, w, lone, clamp)


@njit(cache=True, error_model="numpy")
def _cos_half(radius):
    """(S, J) cos(r / 2) of each clamp radius: unit q is inside where |mean . q| >= that."""
    out = np.empty(radius.shape)
    for s in range(radius.shape[0]):
        for j in range(radius.shape[1]):
            out[s, j] = math.cos(0.5 * min(radius[s, j], math.pi))
    return out


@njit(cache=True, error_model="numpy")
def _gained(p, row, j, w, lone, rest, gain):
    """The fast part p's vector part through the weight-mixed gains, renormalised (~ exp(G log p))."""
    if lone >= 0:
        gx, gy, gz = _mat3(gain, lone, j, p)
    else:
        gx, gy, gz = rest * p[0], rest * p[1], rest * p[2]
        for s in range(w.shape[1]):
            ws = w[row, s]
            if ws != 0.0:
                tx, ty, tz = _mat3(gain, s, j, p)
                gx, gy, gz = gx + ws * tx, gy + ws * ty, gz + ws * tz
    g = (gx, gy, gz, p[3])
    return qscale(g, 1.0 / math.sqrt(qdot(g, g)))


class SlowPriors(NamedTuple):
    """What `carry_slow_batch` carries by: the walk, run and stand carries, `clamp` (also what a
    gait's own carry is followed by), fast gains and `plain` joints."""

    walk: tuple
    run: tuple
    stand: tuple
    clamp: tuple
    gain: np.ndarray
    plain: np.ndarray


@njit(cache=True, error_model="numpy")
def carry_slow_batch(q, slow, weight, w, share, priors, hips, out, new_slow):
    """The slow part of q carried, its fast part on top (`models/erd/slow_carry.py`). Per row and joint:

    s = nlerp(slow, q, weight) on the shorter arc (a row of `slow` all zeros: s = q)
    p = s^-1 q, the fast part, in its short hemisphere
    o = carry(s) (G p_xyz, p_w) / |.|, then o clamped into `clamp`'s range

    carry: walk's, mixed with the run's (share r > 0) or the stand's (r < 0) by |r|, each then
    clamped; G: the gains mixed by w; `plain` joints are carried whole. Writes `out` and `new_slow`."""
    S, J = w.shape[1], q.shape[1]
    a, run, stand, clamp, gain, plain = priors
    cos_half = _cos_half(clamp[3])
    mean = clamp[1]
    for row in range(q.shape[0]):
        lone = _lone(w, row)
        r = share[row]
        b = run
        if r < 0.0:
            b, r = stand, -r
        rest = 1.0
        for s in range(S):
            rest -= w[row, s]
        rest = max(rest, 0.0)
        unset = True
        for j in range(J):
            for ch in range(4):
                if slow[row, j, ch] != 0.0:
                    unset = False
        for j in range(J):
            u = quat_at(q, row, j)
            u = qscale(u, 1.0 / math.sqrt(qdot(u, u)))
            sl = u
            if not unset:
                before = quat_at(slow, row, j)
                k0 = 1.0 - weight
                if qdot(before, u) < 0.0:
                    k0 = -k0
                sl = qscale(before, k0)
                sl = (sl[0] + weight * u[0], sl[1] + weight * u[1], sl[2] + weight * u[2], sl[3] + weight * u[3])
                sl = qscale(sl, 1.0 / max(math.sqrt(qdot(sl, sl)), 1e-12))
            new_slow[row, j, 0], new_slow[row, j, 1], new_slow[row, j, 2], new_slow[row, j, 3] = sl
            is_hips = j == hips
            # written out for both cases: one inlined helper for the two is ~40 % slower
            whole = True
            for s in range(S):
                if w[row, s] != 0.0 and not plain[s, j]:
                    whole = False
            if whole:
                h, heading = _headless(u, is_hips)
                o = (
                    _carry_joint(h, row, j, w, lone, a)
                    if r == 0.0
                    else _paired(h, row, j, w, lone, r, a, b, clamp, cos_half)
                )
                out[row, j, 0], out[row, j, 1], out[row, j, 2], out[row, j, 3] = qmul(heading, o) if is_hips else o
                continue
            # the slow copy, carried
            h, heading = _headless(sl, is_hips)
            o = (
                _carry_joint(h, row, j, w, lone, a)
                if r == 0.0
                else _paired(h, row, j, w, lone, r, a, b, clamp, cos_half)
            )
            if is_hips:
                o = qmul(heading, o)
            # the fast part on top
            p = qmul(qinv(sl), u)
            if p[3] < 0.0:
                p = qneg(p)
            if not is_hips:
                p = _gained(p, row, j, w, lone, rest, gain)
            o = qmul(o, p)
            # the clamp
            h, heading = _headless(qscale(o, 1.0 / math.sqrt(qdot(o, o))), is_hips)
            if lone >= 0 and abs(qdot(quat_at(mean, lone, j), h)) >= cos_half[lone, j]:
                out[row, j, 0], out[row, j, 1], out[row, j, 2], out[row, j, 3] = o
                continue
            h = _clamped(h, row, j, w, lone, clamp)
            out[row, j, 0], out[row, j, 1], out[row, j, 2], out[row, j, 3] = qmul(heading, h) if is_hips else h
    return out, new_slow


def carry_slow(
    q: np.ndarray, slow: np.ndarray, weight: float, w: np.ndarray, share: np.ndarray, priors: SlowPriors, hips: int = -1
) -> tuple[np.ndarray, np.ndarray]:
    """`carry_slow_batch` on any rotations, slow copies, weights and shares: (out, new slow copies)."""
    q = np.ascontiguousarray(q, np.float64)
    w, share = np.ascontiguousarray(w, np.float64), np.ascontiguousarray(share, np.float64)
    slow = np.ascontiguousarray(slow, np.float64)
    out, new_slow = np.empty_like(q), np.empty_like(q)
    return carry_slow_batch(q, slow, float(weight), w, share, priors, hips, out, new_slow)
