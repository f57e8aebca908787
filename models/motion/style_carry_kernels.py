"""`style_carry.StyleCarry` compiled (numba) for the per-frame step: the formulas of the numpy
reference (`tests/reference/erd_carry.py`) as per-row, per-joint loops, ~1 us per session
instead of ~40 small numpy calls per prior and frame. `_toward` and `_carry_joint` are inlined
(`inline="always"`): out of line, passing their arrays as numba structs cost a quarter to a half
of the kernel's time; inlining the small helpers too buys nothing and triples the first compile.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .quaternion import qexp, qinv, qlog, qmul, quat_at


@njit(cache=True, error_model="numpy", inline="always")
def _toward(qx, qy, qz, qw, s, j, source, mean, lin, radius):
    """f_s(q) = mean exp(clamp(M log(src^-1 q))) for joint j and style s."""
    lx, ly, lz = qlog(qmul(qinv(quat_at(source, s, j)), (qx, qy, qz, qw)))
    dx = lin[s, j, 0, 0] * lx + lin[s, j, 0, 1] * ly + lin[s, j, 0, 2] * lz
    dy = lin[s, j, 1, 0] * lx + lin[s, j, 1, 1] * ly + lin[s, j, 1, 2] * lz
    dz = lin[s, j, 2, 0] * lx + lin[s, j, 2, 1] * ly + lin[s, j, 2, 2] * lz
    dn = math.sqrt(dx * dx + dy * dy + dz * dz)
    r = radius[s, j]
    if dn > r:
        k = r / dn
        dx, dy, dz = k * dx, k * dy, k * dz
    return qmul(quat_at(mean, s, j), qexp((dx, dy, dz)))


@njit(cache=True, error_model="numpy")
def _correction(qx, qy, qz, qw, fx, fy, fz, fw):
    """log(q^-1 f): the rotation vector taking q to f."""
    return qlog(qmul(qinv((qx, qy, qz, qw)), (fx, fy, fz, fw)))


@njit(cache=True, error_model="numpy")
def _lone(w, b):
    """Row b's one style at weight 1 if that is all it has (no mix, no intensity), else < 0."""
    lone = -1
    for s in range(w.shape[1]):
        if w[b, s] != 0.0:
            lone = s if lone == -1 and w[b, s] == 1.0 else -2
    return lone


@njit(cache=True, error_model="numpy", inline="always")
def _headless(qx, qy, qz, qw, is_hips):
    """Unit q without its heading when it is the Hips (heading = (0, hy, 0, hw)): (q', hy, hw)."""
    hy, hw = 0.0, 1.0
    if is_hips:
        hn = math.sqrt(qy * qy + qw * qw)
        if hn > 1e-9:
            hy, hw = qy / hn, qw / hn
        qx, qy, qz, qw = qmul((0.0, -hy, 0.0, hw), (qx, qy, qz, qw))
    return qx, qy, qz, qw, hy, hw


@njit(cache=True, error_model="numpy")
def _unit(q, b, j, hips):
    """q[b, j] normalised, and for joint `hips` without its heading (its twist about world up):
    (qx, qy, qz, qw, hy, hw), the heading being (0, hy, 0, hw) (identity for other joints)."""
    n = math.sqrt(q[b, j, 0] ** 2 + q[b, j, 1] ** 2 + q[b, j, 2] ** 2 + q[b, j, 3] ** 2)
    return _headless(q[b, j, 0] / n, q[b, j, 1] / n, q[b, j, 2] / n, q[b, j, 3] / n, j == hips)


@njit(cache=True, error_model="numpy")
def _store(out, b, j, hips, hy, hw, ox, oy, oz, ow):
    """out[b, j] = o, with the heading `_unit` took off joint `hips` put back."""
    if j == hips:
        ox, oy, oz, ow = qmul((0.0, hy, 0.0, hw), (ox, oy, oz, ow))
    out[b, j, 0], out[b, j, 1], out[b, j, 2], out[b, j, 3] = ox, oy, oz, ow


@njit(cache=True, error_model="numpy")
def _same_side(qx, qy, qz, qw, ox, oy, oz, ow):
    """o in q's hemisphere (the same rotation): a stream's quaternions never flip sign."""
    if ox * qx + oy * qy + oz * qz + ow * qw < 0.0:
        return -ox, -oy, -oz, -ow
    return ox, oy, oz, ow


@njit(cache=True, error_model="numpy", inline="always")
def _carry_joint(qx, qy, qz, qw, b, j, w, lone, source, mean, lin, radius):
    """Unit quaternion q of row b, joint j carried toward the styles of w[b] (`carry_batch`)."""
    if lone >= 0:
        fx, fy, fz, fw = _toward(qx, qy, qz, qw, lone, j, source, mean, lin, radius)
        return _same_side(qx, qy, qz, qw, fx, fy, fz, fw)
    cx = cy = cz = 0.0
    for s in range(w.shape[1]):
        ws = w[b, s]
        if ws == 0.0:
            continue
        fx, fy, fz, fw = _toward(qx, qy, qz, qw, s, j, source, mean, lin, radius)
        lx, ly, lz = _correction(qx, qy, qz, qw, fx, fy, fz, fw)  # weighted
        cx += ws * lx
        cy += ws * ly
        cz += ws * lz
    return qmul((qx, qy, qz, qw), qexp((cx, cy, cz)))


@njit(cache=True, error_model="numpy")
def carry_batch(q, w, source, mean, lin, radius, hips, out):
    """out (B, J, 4) = q (B, J, 4) carried toward the styles of weights w (B, S). Joint `hips`
    (-1: none) is carried without its heading, its twist about world up (+Y), which is put back
    after (`tests/reference/erd_carry.py` is the numpy reference). A row with one style at
    weight 1 (no mix, no intensity) takes f_s(q) itself, in q's hemisphere: the blend
    q exp(log(q^-1 f_s(q))) is the same rotation, and skipping its log and exp halves the
    kernel's cost for such rows."""
    for b in range(q.shape[0]):
        lone = _lone(w, b)
        for j in range(q.shape[1]):
            qx, qy, qz, qw, hy, hw = _unit(q, b, j, hips)
            ox, oy, oz, ow = _carry_joint(qx, qy, qz, qw, b, j, w, lone, source, mean, lin, radius)
            _store(out, b, j, hips, hy, hw, ox, oy, oz, ow)
    return out


def carry(q: np.ndarray, w: np.ndarray, source, mean, lin, radius, hips: int = -1) -> np.ndarray:
    """`carry_batch` on any (B, J, 4) rotations and (B, S) weights."""
    q = np.ascontiguousarray(q, np.float64)
    out = np.empty_like(q)
    return carry_batch(q, np.ascontiguousarray(w, np.float64), source, mean, lin, radius, hips, out)


@njit(cache=True, error_model="numpy", inline="always")
def _pair_joint(qx, qy, qz, qw, row, j, w, lone, r, a, b, c):
    """Unit quaternion q of row `row`, joint j carried by `a` and by `b` then `c`, mixed by the
    row's share r (`carry_pair_batch`)."""
    if r == 0.0:
        return _carry_joint(qx, qy, qz, qw, row, j, w, lone, a[0], a[1], a[2], a[3])
    if lone >= 0 and r == 1.0:
        bx, by, bz, bw = _toward(qx, qy, qz, qw, lone, j, b[0], b[1], b[2], b[3])
        fx, fy, fz, fw = _toward(bx, by, bz, bw, lone, j, c[0], c[1], c[2], c[3])
        return _same_side(qx, qy, qz, qw, fx, fy, fz, fw)
    cx = cy = cz = 0.0
    for s in range(w.shape[1]):
        ws = w[row, s]
        if ws == 0.0:
            continue
        if r < 1.0:
            fx, fy, fz, fw = _toward(qx, qy, qz, qw, s, j, a[0], a[1], a[2], a[3])
            lx, ly, lz = _correction(qx, qy, qz, qw, fx, fy, fz, fw)
            k = ws * (1.0 - r)
            cx, cy, cz = cx + k * lx, cy + k * ly, cz + k * lz
        bx, by, bz, bw = _toward(qx, qy, qz, qw, s, j, b[0], b[1], b[2], b[3])
        fx, fy, fz, fw = _toward(bx, by, bz, bw, s, j, c[0], c[1], c[2], c[3])
        lx, ly, lz = _correction(qx, qy, qz, qw, fx, fy, fz, fw)
        k = ws * r
        cx, cy, cz = cx + k * lx, cy + k * ly, cz + k * lz
    return qmul((qx, qy, qz, qw), qexp((cx, cy, cz)))


@njit(cache=True, error_model="numpy")
def carry_pair_batch(q, w, share, a, b, c, hips, out):
    """out (B, J, 4): each row's rotations carried toward the styles of w (B, S) by two carries
    mixed by the row's share (B,) in [0, 1]: carry `a` (source, mean, lin, radius) and carry `b`
    followed by carry `c`, both with the row's weights:

        q exp(sum_s w_s [(1 - r) log(q^-1 a_s(q)) + r log(q^-1 c_s(b_s(q)))])

    A row with one style at weight 1 and share 0 or 1 takes a_s(q) or c_s(b_s(q)) itself, in
    q's hemisphere (the same rotation, without the log and exp); at share 0 every row is what
    `carry_batch` with `a` gives it. Joint `hips` as in `carry_batch`."""
    for row in range(q.shape[0]):
        lone = _lone(w, row)
        for j in range(q.shape[1]):
            qx, qy, qz, qw, hy, hw = _unit(q, row, j, hips)
            ox, oy, oz, ow = _pair_joint(qx, qy, qz, qw, row, j, w, lone, share[row], a, b, c)
            _store(out, row, j, hips, hy, hw, ox, oy, oz, ow)
    return out


def carry_pair(
    q: np.ndarray, w: np.ndarray, share: np.ndarray, a: tuple, b: tuple, c: tuple, hips: int = -1
) -> np.ndarray:
    """`carry_pair_batch` on any (B, J, 4) rotations, (B, S) weights and (B,) shares; a, b, c:
    (source, mean, lin, radius) of each carry."""
    q = np.ascontiguousarray(q, np.float64)
    out = np.empty_like(q)
    w, share = np.ascontiguousarray(w, np.float64), np.ascontiguousarray(share, np.float64)
    return carry_pair_batch(q, w, share, a, b, c, hips, out)


@njit(cache=True, error_model="numpy")
def _paired(qx, qy, qz, qw, row, j, w, lone, r, a, b, c):
    """`_pair_joint` out of line, for the rows with a share (runs): inlined beside the plain
    carry it made `carry_slow_batch` twice as slow for every row."""
    return _pair_joint(qx, qy, qz, qw, row, j, w, lone, r, a, b, c)


@njit(cache=True, error_model="numpy")
def _clamped(qx, qy, qz, qw, row, j, w, lone, clamp):
    """q kept in the range of `clamp` (source, mean, lin, radius of `StyleCarry.bounds`), as
    `carry_batch` keeps it; out of line (most joints are inside and skip it), so the caller's
    loop stays small."""
    return _carry_joint(qx, qy, qz, qw, row, j, w, lone, clamp[0], clamp[1], clamp[2], clamp[3])


@njit(cache=True, error_model="numpy")
def _cos_half(radius):
    """(S, J) cos(r / 2) of each clamp radius r: a unit q is inside it where |mean . q| >= that."""
    out = np.empty(radius.shape)
    for s in range(radius.shape[0]):
        for j in range(radius.shape[1]):
            out[s, j] = math.cos(0.5 * min(radius[s, j], math.pi))
    return out


@njit(cache=True, error_model="numpy")
def carry_slow_batch(q, slow, weight, w, share, a, b, c, clamp, gain, plain, hips, out, new_slow):
    """The slow part of q carried, its fast part on top (`models/erd/slow_carry.py`), in one
    pass. Per row and joint:

        s = nlerp(slow, q, weight) on the shorter arc (a row of `slow` all zeros: s = q)
        p = s^-1 q, the fast part, in its short hemisphere
        o = carry(s) (G p_xyz, p_w) / |.|, then o clamped into `clamp`'s range

    carry: `a` and `b`-then-`c` mixed by the row's share, as `carry_pair_batch`; G: the gains
    (S, J, 3, 3) mixed by the row's weights w (B, S), the rest of the weight at 1 (joint `hips`:
    1, its fast part holds its turning); to first order in the fast part's angle
    (G p_xyz, p_w) / |.| is exp(G log p), without a log or an exp. `clamp`: a range alone
    (`StyleCarry.bounds`); a row with one style skips its arithmetic for a joint already inside
    (the clamp leaves it as it is). Joint `hips` is carried and clamped without its heading, as
    in `carry_batch`. A joint marked `plain` (J,) bool (one `a` leaves as it is, only clamps:
    the same either way) is carried whole, as `carry_pair_batch` would. Writes `out` and the new
    slow copies `new_slow`."""
    S, J = w.shape[1], q.shape[1]
    cos_half = _cos_half(clamp[3])
    mean = clamp[1]
    for row in range(q.shape[0]):
        lone = _lone(w, row)
        r = share[row]
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
            k = 1.0 / math.sqrt(q[row, j, 0] ** 2 + q[row, j, 1] ** 2 + q[row, j, 2] ** 2 + q[row, j, 3] ** 2)
            ux, uy, uz, uw = k * q[row, j, 0], k * q[row, j, 1], k * q[row, j, 2], k * q[row, j, 3]
            sx, sy, sz, sw = ux, uy, uz, uw
            if not unset:
                k0 = 1.0 - weight
                if slow[row, j, 0] * ux + slow[row, j, 1] * uy + slow[row, j, 2] * uz + slow[row, j, 3] * uw < 0.0:
                    k0 = -k0
                sx = k0 * slow[row, j, 0] + weight * ux
                sy = k0 * slow[row, j, 1] + weight * uy
                sz = k0 * slow[row, j, 2] + weight * uz
                sw = k0 * slow[row, j, 3] + weight * uw
                k = 1.0 / max(math.sqrt(sx * sx + sy * sy + sz * sz + sw * sw), 1e-12)
                sx, sy, sz, sw = k * sx, k * sy, k * sz, k * sw
            new_slow[row, j, 0], new_slow[row, j, 1], new_slow[row, j, 2], new_slow[row, j, 3] = sx, sy, sz, sw
            is_hips = j == hips
            # the carry is written out for both cases below: one inlined helper for the two makes
            # the pass ~40 % slower (numba's inlining)
            if plain[j]:
                hx, hy_, hz, hw_, hy, hw = _headless(ux, uy, uz, uw, is_hips)
                if r == 0.0:
                    cx, cy, cz, cw = _carry_joint(hx, hy_, hz, hw_, row, j, w, lone, a[0], a[1], a[2], a[3])
                else:
                    cx, cy, cz, cw = _paired(hx, hy_, hz, hw_, row, j, w, lone, r, a, b, c)
                if is_hips:
                    cx, cy, cz, cw = qmul((0.0, hy, 0.0, hw), (cx, cy, cz, cw))
                out[row, j, 0], out[row, j, 1], out[row, j, 2], out[row, j, 3] = cx, cy, cz, cw
                continue
            # the slow copy, carried
            hx, hy_, hz, hw_, hy, hw = _headless(sx, sy, sz, sw, is_hips)
            if r == 0.0:
                cx, cy, cz, cw = _carry_joint(hx, hy_, hz, hw_, row, j, w, lone, a[0], a[1], a[2], a[3])
            else:
                cx, cy, cz, cw = _paired(hx, hy_, hz, hw_, row, j, w, lone, r, a, b, c)
            if is_hips:
                cx, cy, cz, cw = qmul((0.0, hy, 0.0, hw), (cx, cy, cz, cw))
            # the fast part on top
            px, py, pz, pw = qmul(qinv((sx, sy, sz, sw)), (ux, uy, uz, uw))
            if pw < 0.0:
                px, py, pz, pw = -px, -py, -pz, -pw
            if not is_hips:
                if lone >= 0:
                    g = gain[lone, j]
                    gx = g[0, 0] * px + g[0, 1] * py + g[0, 2] * pz
                    gy = g[1, 0] * px + g[1, 1] * py + g[1, 2] * pz
                    gz = g[2, 0] * px + g[2, 1] * py + g[2, 2] * pz
                else:
                    gx, gy, gz = rest * px, rest * py, rest * pz
                    for s in range(S):
                        ws = w[row, s]
                        if ws != 0.0:
                            gx += ws * (gain[s, j, 0, 0] * px + gain[s, j, 0, 1] * py + gain[s, j, 0, 2] * pz)
                            gy += ws * (gain[s, j, 1, 0] * px + gain[s, j, 1, 1] * py + gain[s, j, 1, 2] * pz)
                            gz += ws * (gain[s, j, 2, 0] * px + gain[s, j, 2, 1] * py + gain[s, j, 2, 2] * pz)
                k = 1.0 / math.sqrt(gx * gx + gy * gy + gz * gz + pw * pw)
                px, py, pz, pw = k * gx, k * gy, k * gz, k * pw
            ox, oy, oz, ow = qmul((cx, cy, cz, cw), (px, py, pz, pw))
            # the clamp
            k = 1.0 / math.sqrt(ox * ox + oy * oy + oz * oz + ow * ow)
            qx, qy, qz, qw, hy, hw = _headless(k * ox, k * oy, k * oz, k * ow, is_hips)
            if lone >= 0:
                d = mean[lone, j, 0] * qx + mean[lone, j, 1] * qy + mean[lone, j, 2] * qz + mean[lone, j, 3] * qw
                if abs(d) >= cos_half[lone, j]:
                    out[row, j, 0], out[row, j, 1], out[row, j, 2], out[row, j, 3] = ox, oy, oz, ow
                    continue
            qx, qy, qz, qw = _clamped(qx, qy, qz, qw, row, j, w, lone, clamp)
            if is_hips:
                qx, qy, qz, qw = qmul((0.0, hy, 0.0, hw), (qx, qy, qz, qw))
            out[row, j, 0], out[row, j, 1], out[row, j, 2], out[row, j, 3] = qx, qy, qz, qw
    return out, new_slow


def carry_slow(
    q: np.ndarray, slow: np.ndarray, weight: float, w: np.ndarray, share: np.ndarray, a: tuple, b: tuple, c: tuple,
    clamp: tuple, gain: np.ndarray, plain: np.ndarray, hips: int = -1,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """`carry_slow_batch` on any (B, J, 4) rotations and slow copies, (B, S) weights and (B,)
    shares; a, b, c, clamp: (source, mean, lin, radius) of each carry. Returns (out, new slow
    copies)."""
    q = np.ascontiguousarray(q, np.float64)
    w, share = np.ascontiguousarray(w, np.float64), np.ascontiguousarray(share, np.float64)
    slow = np.ascontiguousarray(slow, np.float64)
    out, new_slow = np.empty_like(q), np.empty_like(q)
    return carry_slow_batch(q, slow, float(weight), w, share, a, b, c, clamp, gain, plain, hips, out, new_slow)
