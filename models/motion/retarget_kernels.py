"""Compiled kernels (numba) for `retarget_stream.FrameRetargeter`: one frame at a time on scalars.

A few microseconds a character at batch 1 (the numpy reference, `tests/reference/retarget.py`,
spends ~2 ms in small calls); the maths is the reference's step for step, equal to round-off.
A rig's arrays are packed into one int and one float buffer (`pack`).

Conventions: quaternions (x, y, z, w); matrices act on column vectors; slots are the client's
needed joints in depth order (`retarget_stream._Tree`), slot -1 meaning "identity".
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from .retarget import HINGE_FALLBACK, HINGE_PRIOR, TWIST_SHARE

KINDS = ("leaf", "swing", "limb", "clavicle")  # a `TwistPlan` group's kind -> its number here, its index
KIND_LEAF, KIND_SWING, KIND_LIMB, KIND_CLAVICLE = range(len(KINDS))
HINGE_FALLBACK_SQ = HINGE_FALLBACK**2

# --------------------------------------------------------------------------- 3x3 helpers
# Inlined: a call on views costs reference counting, ~3x the arithmetic.


@njit(cache=True, error_model="numpy", inline="always")
def _mm(a, b, out):
    """out = a @ b (3x3); out may not alias a or b."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@njit(cache=True, error_model="numpy", inline="always")
def _mtm(a, b, out):
    """out = a.T @ b (3x3)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[0, i] * b[0, j] + a[1, i] * b[1, j] + a[2, i] * b[2, j]


@njit(cache=True, error_model="numpy", inline="always")
def _mmt(a, b, out):
    """out = a @ b.T (3x3)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[j, 0] + a[i, 1] * b[j, 1] + a[i, 2] * b[j, 2]


@njit(cache=True, error_model="numpy", inline="always")
def _mv(a, v, out):
    """out = a @ v."""
    for i in range(3):
        out[i] = a[i, 0] * v[0] + a[i, 1] * v[1] + a[i, 2] * v[2]


@njit(cache=True, error_model="numpy", inline="always")
def _eye(out):
    for i in range(3):
        for j in range(3):
            out[i, j] = 1.0 if i == j else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _quat_to_mat(q, out):
    """(4,) quaternion (normalised here) -> 3x3 (rotations.quat_to_matrix)."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    s = 2.0 / (x * x + y * y + z * z + w * w)  # 2 / |q|^2: the products of the unit quaternion, doubled
    xx, yy, zz, xy, xz, yz, wx, wy, wz = (
        s * x * x, s * y * y, s * z * z, s * x * y, s * x * z, s * y * z, s * w * x, s * w * y, s * w * z
    )  # fmt: skip
    out[0, 0], out[0, 1], out[0, 2] = 1 - (yy + zz), xy - wz, xz + wy
    out[1, 0], out[1, 1], out[1, 2] = xy + wz, 1 - (xx + zz), yz - wx
    out[2, 0], out[2, 1], out[2, 2] = xz - wy, yz + wx, 1 - (xx + yy)


@njit(cache=True, error_model="numpy", inline="always")
def _mat_to_quat(m, out):
    """3x3 -> (4,) quaternion with w >= 0 (Shepperd's method, as rotations.matrix_to_quat)."""
    m00, m11, m22 = m[0, 0], m[1, 1], m[2, 2]
    trace = m00 + m11 + m22
    best, big = 0, trace
    if m00 > big:
        best, big = 1, m00
    if m11 > big:
        best, big = 2, m11
    if m22 > big:
        best = 3
    if best == 0:
        x, y, z, w = m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1 + trace
    elif best == 1:
        x, y, z, w = 1 + m00 - m11 - m22, m[0, 1] + m[1, 0], m[0, 2] + m[2, 0], m[2, 1] - m[1, 2]
    elif best == 2:
        x, y, z, w = m[0, 1] + m[1, 0], 1 + m11 - m00 - m22, m[1, 2] + m[2, 1], m[0, 2] - m[2, 0]
    else:
        x, y, z, w = m[0, 2] + m[2, 0], m[1, 2] + m[2, 1], 1 + m22 - m00 - m11, m[1, 0] - m[0, 1]
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if w < 0:
        n = -n
    out[0], out[1], out[2], out[3] = x / n, y / n, z / n, w / n


@njit(cache=True, error_model="numpy", inline="always")
def _world_of(g, p, c, q, m):
    """g[c] = g[p] @ R(q), the world rotation of joint c from its parent's (p < 0: a root, R(q))."""
    if p < 0:
        _quat_to_mat(q, g[c])
    else:
        _quat_to_mat(q, m)
        _mm(g[p], m, g[c])


@njit(cache=True, error_model="numpy", inline="always")
def _local_of(g, p, c, m, out):
    """out = the local quaternion of joint c, g[p].T @ g[c] (p < 0: a root, g[c])."""
    if p < 0:
        _mat_to_quat(g[c], out)
    else:
        _mtm(g[p], g[c], m)
        _mat_to_quat(m, out)


@njit(cache=True, error_model="numpy", inline="always")
def _frame(p0, p1, p2, l0, l1, l2, out):
    """retarget._frame: columns (primary, lateral made orthogonal, their cross), all unit."""
    n = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    a0, a1, a2 = p0 / n, p1 / n, p2 / n
    d = l0 * a0 + l1 * a1 + l2 * a2
    b0, b1, b2 = l0 - d * a0, l1 - d * a1, l2 - d * a2
    n = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    b0, b1, b2 = b0 / n, b1 / n, b2 / n
    out[0, 0], out[1, 0], out[2, 0] = a0, a1, a2
    out[0, 1], out[1, 1], out[2, 1] = b0, b1, b2
    out[0, 2], out[1, 2], out[2, 2] = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, error_model="numpy", inline="always")
def _swing(a, b, out):
    """The smallest rotation taking unit a to unit b (opposite: a half turn)."""
    v0, v1, v2 = a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]
    c = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    lin = 1.0
    if c < -1.0 + 1e-9:
        if abs(a[0]) < 0.9:  # cross(a, x)
            v0, v1, v2 = 0.0, a[2], -a[1]
        else:  # cross(a, y)
            v0, v1, v2 = -a[2], 0.0, a[0]
        n = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        v0, v1, v2 = v0 / n, v1 / n, v2 / n
        lin, s = 0.0, 1.0
    else:
        s = 1.0 / (1.0 + c)
    # [v]x and [v]x^2 = v v^T - |v|^2 I
    vv = v0 * v0 + v1 * v1 + v2 * v2
    out[0, 0] = 1.0 + s * (v0 * v0 - vv)
    out[1, 1] = 1.0 + s * (v1 * v1 - vv)
    out[2, 2] = 1.0 + s * (v2 * v2 - vv)
    out[0, 1] = -lin * v2 + s * v0 * v1
    out[1, 0] = lin * v2 + s * v0 * v1
    out[0, 2] = lin * v1 + s * v0 * v2
    out[2, 0] = -lin * v1 + s * v0 * v2
    out[1, 2] = -lin * v0 + s * v1 * v2
    out[2, 1] = lin * v0 + s * v1 * v2


@njit(cache=True, error_model="numpy", inline="always")
def _split_twist(g, gc, nat_c, b, m, dev, r):
    """g turned by TWIST_SHARE of the child's twist about bone b (retarget.TwistPlan's "split")."""
    _mtm(g, gc, m)
    _mmt(m, nat_c, dev)
    v = (dev[2, 1] - dev[1, 2]) * b[0] + (dev[0, 2] - dev[2, 0]) * b[1] + (dev[1, 0] - dev[0, 1]) * b[2]
    a = TWIST_SHARE * 2.0 * np.arctan2(v, 1.0 + dev[0, 0] + dev[1, 1] + dev[2, 2])
    sn, cs = np.sin(a), 1.0 - np.cos(a)
    # Rodrigues: I + sin K + (1 - cos) K^2, K = [b]x, K^2 = b b^T - I
    for i in range(3):
        for k in range(3):
            r[i, k] = cs * b[i] * b[k] + (1.0 - cs if i == k else 0.0)
    r[0, 1] -= sn * b[2]
    r[1, 0] += sn * b[2]
    r[0, 2] += sn * b[1]
    r[2, 0] -= sn * b[1]
    r[1, 2] -= sn * b[0]
    r[2, 1] += sn * b[0]
    _mm(g, r, m)
    g[:, :] = m


@njit(cache=True, error_model="numpy")
def _bn_lowest(gb, drop_par, drop_off, drop_ref):
    """The lowest BN foot point's height below the Hips, each off its standing height (`_drop`)."""
    low = np.inf
    for i in range(drop_par.shape[0]):
        y = -drop_ref[1, i]
        for q in range(drop_par.shape[1]):
            p = drop_par[i, q]
            if p < 0:
                break
            y += gb[p, 1, 0] * drop_off[i, q, 0] + gb[p, 1, 1] * drop_off[i, q, 1] + gb[p, 1, 2] * drop_off[i, q, 2]
        low = min(low, y)
    return low


class Rig(NamedTuple):
    """What the kernels read of a rig (`FrameRetargeter._kernel_plan`); slots in depth order."""

    src_order: np.ndarray  # (Ns,) client joint of each slot
    src_par_s: np.ndarray  # (Ns,) its parent's slot (-1: a root)
    fixed_par_s: np.ndarray  # the chain above the client's hips: parent slots ...
    fixed_off: np.ndarray  # ... and offsets (`_hips_terms`)
    translated_par_s: int  # slot of the translated joint's parent (-1: none)
    vec_par_s: np.ndarray  # segment terms: parent slot of each ...
    vec_off: np.ndarray  # ... and its offset
    vec_nz: np.ndarray  # (E, 2) (segment vector, term) entries ...
    vec_w: np.ndarray  # ... and their weights
    axes: np.ndarray  # (3, 3) the client's world to BN's
    num_plain: int  # segment vectors that are bone directions (then two per lateral joint, then foot points)
    m_tgt_t: np.ndarray  # two-vector joints (Hips, Chest): target frame transposed ...
    lateral_j: np.ndarray  # ... and BN joint
    step_i: np.ndarray  # (S, 8) per other joint: kind, joint, parent, segment, limb plane segment, split child,
    # and for a limb the client slot whose frame holds its hinge axis and the hinge's row in the state
    step_nat: np.ndarray  # its natural local rotation
    step_b: np.ndarray  # its bone direction
    step_k: np.ndarray  # its natural hinge axis
    step_m_loc_t: np.ndarray  # its frame from the limb plane
    step_split_nat: np.ndarray  # its split child's natural rotation
    bn_parents: np.ndarray  # (22,)
    bn_fixed_q: np.ndarray  # (22, 4) local rotations kept as they are (w < 0: computed)
    bn_order: np.ndarray  # BN joints, parents first
    delta_j: np.ndarray  # BN joints whose change some client joint takes
    anc_bn_s: np.ndarray  # per slot, that BN joint (22: none)
    mapped_j: np.ndarray  # mapped client joints ...
    mapped_s: np.ndarray  # ... their slots ...
    mapped_par_s: np.ndarray  # ... and their parents' slots (-1: a mapped root)
    drop_par: np.ndarray  # foot points: parent chains ...
    drop_off: np.ndarray  # ... offsets ...
    drop_ref: np.ndarray  # ... and reference heights (`FrameRetargeter._drop`)
    step_reach: np.ndarray  # (S,) a limb's lower bone length over its upper (`_hinged`)


# --------------------------------------------------------------------------- per-frame steps
# Scratch arrays come from the callers (allocated once per call, not per frame): w33 (3, 3, 3), w3 (3, 3).


@njit(cache=True, error_model="numpy")
def _source_fk(rot, order, par_s, gs, m):
    """Client world rotations in slots: gs[s] = gs[par_s[s]] @ R(rot[order[s]]) (par_s -1: a root)."""
    for s in range(order.shape[0]):
        _world_of(gs, par_s[s], s, rot[order[s]], m)


@njit(cache=True, error_model="numpy")
def _hips_terms(gs, fixed_par_s, fixed_off, translated_par_s, c, gp, t):
    """The client hips' world position is c + gp @ root."""
    c[:] = 0.0
    for i in range(fixed_par_s.shape[0]):
        if fixed_par_s[i] < 0:
            for r in range(3):
                c[r] += fixed_off[i, r]
        else:
            _mv(gs[fixed_par_s[i]], fixed_off[i], t)
            for r in range(3):
                c[r] += t[r]
    if translated_par_s < 0:
        _eye(gp)
    else:
        gp[:, :] = gs[translated_par_s]


@njit(cache=True, error_model="numpy", inline="always")
def _hinge_fallback(g, axes, hinge, fold, n0, n1, n2, nat):
    """nat := the unit mean of BN's natural hinge axis and the client's learned one (`HINGE_FALLBACK`);
    `hinge` (4,): the sin^2-weighted axis sum in its joint's frame and the weights' sum."""
    if fold:
        s2 = n0 * n0 + n1 * n1 + n2 * n2
        p = 0.0
        if hinge[3] == 0.0:  # a fresh stream: the natural axis as it stands now, carried by g from here on
            p = HINGE_PRIOR
        v0, v1, v2 = s2 * n0 + p * nat[0], s2 * n1 + p * nat[1], s2 * n2 + p * nat[2]
        a0 = axes[0, 0] * v0 + axes[1, 0] * v1 + axes[2, 0] * v2  # axes.T @ v: the client's world
        a1 = axes[0, 1] * v0 + axes[1, 1] * v1 + axes[2, 1] * v2
        a2 = axes[0, 2] * v0 + axes[1, 2] * v1 + axes[2, 2] * v2
        for r in range(3):  # g.T @ (axes.T @ v)
            hinge[r] += g[0, r] * a0 + g[1, r] * a1 + g[2, r] * a2
        hinge[3] += s2 + p
    k = np.sqrt(hinge[0] * hinge[0] + hinge[1] * hinge[1] + hinge[2] * hinge[2])
    if k == 0.0:  # nothing learned (`to_source` on a fresh state)
        return
    a0 = (g[0, 0] * hinge[0] + g[0, 1] * hinge[1] + g[0, 2] * hinge[2]) / k  # g @ hinge: the client's world
    a1 = (g[1, 0] * hinge[0] + g[1, 1] * hinge[1] + g[1, 2] * hinge[2]) / k
    a2 = (g[2, 0] * hinge[0] + g[2, 1] * hinge[1] + g[2, 2] * hinge[2]) / k
    m0 = nat[0] + axes[0, 0] * a0 + axes[0, 1] * a1 + axes[0, 2] * a2
    m1 = nat[1] + axes[1, 0] * a0 + axes[1, 1] * a1 + axes[1, 2] * a2
    m2 = nat[2] + axes[2, 0] * a0 + axes[2, 1] * a1 + axes[2, 2] * a2
    m = np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    if m > 1e-9:  # else (the two exactly opposed): the natural axis
        nat[0], nat[1], nat[2] = m0 / m, m1 / m, m2 / m


@njit(cache=True, error_model="numpy")
def _bn_globals(gs, rig, gb, terms, raw, vec, w33, w3, hinges, fold):
    """BN world rotations gb (22, 3, 3) from the client's slot rotations gs."""
    for t in range(rig.vec_off.shape[0]):
        _mv(gs[rig.vec_par_s[t]], rig.vec_off[t], terms[t])
    same_axes = rig.axes[0, 0] == 1.0 and rig.axes[1, 1] == 1.0 and rig.axes[2, 2] == 1.0  # the client's world is BN's
    acc = vec if same_axes else raw
    acc[:, :] = 0.0
    for e in range(rig.vec_nz.shape[0]):
        v, t, w = rig.vec_nz[e, 0], rig.vec_nz[e, 1], rig.vec_w[e]
        for r in range(3):
            acc[v, r] += w * terms[t, r]
    if not same_axes:
        for v in range(raw.shape[0]):
            _mv(rig.axes, raw[v], vec[v])  # in BN's world
    for v in range(rig.num_plain):  # bone directions
        n = 1.0 / np.sqrt(vec[v, 0] * vec[v, 0] + vec[v, 1] * vec[v, 1] + vec[v, 2] * vec[v, 2])
        for r in range(3):
            vec[v, r] *= n

    m, base, sw = w33[0], w33[1], w33[2]
    bone, nat = w3[0], w3[1]
    for j in range(rig.bn_parents.shape[0]):
        if rig.bn_parents[j] < 0:
            _eye(gb[j])  # joint_Root
    for i in range(rig.lateral_j.shape[0]):  # two-vector joints (Hips, Chest)
        a, b = rig.num_plain + 2 * i, rig.num_plain + 2 * i + 1
        _frame(vec[a, 0], vec[a, 1], vec[a, 2], vec[b, 0], vec[b, 1], vec[b, 2], m)
        _mm(m, rig.m_tgt_t[i], gb[rig.lateral_j[i]])
    step_i = rig.step_i
    for s in range(step_i.shape[0]):  # every other joint, parents first
        kind, j, p, col, col_c = step_i[s, 0], step_i[s, 1], step_i[s, 2], step_i[s, 3], step_i[s, 4]
        if kind == KIND_LEAF:
            _mm(gb[p], rig.step_nat[s], gb[j])
            continue
        _mm(gb[p], rig.step_nat[s], base)  # natural local rotation under the BN parent
        _mv(base, rig.step_b[s], bone)
        d = vec[col]
        if kind == KIND_CLAVICLE:  # d is the upper arm's direction; A and c ride in the limb slots
            _clavicle(gb[p], d, rig.step_m_loc_t[s], rig.step_k[s], w3[2])
            d = w3[2]
        _swing(bone, d, sw)
        if kind != KIND_LIMB:
            _mm(sw, base, gb[j])
            if step_i[s, 5] >= 0:  # take a share of the two-vector child's twist about the bone
                _split_twist(gb[j], gb[step_i[s, 5]], rig.step_split_nat[s], rig.step_b[s], m, base, sw)
        else:
            # the natural hinge axis, swung: sw @ base @ k (scalar indexing, no views)
            for r in range(3):
                bone[r] = base[r, 0] * rig.step_k[s, 0] + base[r, 1] * rig.step_k[s, 1] + base[r, 2] * rig.step_k[s, 2]
            for r in range(3):
                nat[r] = sw[r, 0] * bone[0] + sw[r, 1] * bone[1] + sw[r, 2] * bone[2]
            lo = vec[col_c]
            n0, n1, n2 = d[1] * lo[2] - d[2] * lo[1], d[2] * lo[0] - d[0] * lo[2], d[0] * lo[1] - d[1] * lo[0]
            w = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)  # the plane's normal weighs its sine: |n| n
            _hinge_fallback(gs[step_i[s, 6]], rig.axes, hinges[step_i[s, 7]], fold, n0, n1, n2, nat)
            _frame(
                d[0],
                d[1],
                d[2],
                w * n0 + HINGE_FALLBACK_SQ * nat[0],
                w * n1 + HINGE_FALLBACK_SQ * nat[1],
                w * n2 + HINGE_FALLBACK_SQ * nat[2],
                m,
            )
            _mm(m, rig.step_m_loc_t[s], gb[j])
            _hinged(gb[j], m, d, vec[col_c], rig.step_reach[s], bone, nat, sw, base)


@njit(cache=True, error_model="numpy", inline="always")
def _clavicle(g, u, a, c, out):
    """The unit clavicle bone for upper arm u under the chest g: g (A g.T u + c), normalised."""
    v0 = g[0, 0] * u[0] + g[1, 0] * u[1] + g[2, 0] * u[2]  # g.T u
    v1 = g[0, 1] * u[0] + g[1, 1] * u[1] + g[2, 1] * u[2]
    v2 = g[0, 2] * u[0] + g[1, 2] * u[1] + g[2, 2] * u[2]
    w0 = a[0, 0] * v0 + a[0, 1] * v1 + a[0, 2] * v2 + c[0]
    w1 = a[1, 0] * v0 + a[1, 1] * v1 + a[1, 2] * v2 + c[1]
    w2 = a[2, 0] * v0 + a[2, 1] * v1 + a[2, 2] * v2 + c[2]
    n = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    for r in range(3):
        out[r] = (g[r, 0] * w0 + g[r, 1] * w1 + g[r, 2] * w2) / n


@njit(cache=True, error_model="numpy", inline="always")
def _hinged(g, frame, d, lo, reach, a, b, sw, m):
    """Limb root g re-framed so the lower bone lies in the hinge plane, the limb's end kept."""
    t = lo[0] * frame[0, 1] + lo[1] * frame[1, 1] + lo[2] * frame[2, 1]
    p0, p1, p2 = lo[0] - t * frame[0, 1], lo[1] - t * frame[1, 1], lo[2] - t * frame[2, 1]
    n = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    if n < 1e-6:  # the lower bone along the hinge axis: no plane to lay it in
        return
    p0, p1, p2 = p0 / n, p1 / n, p2 / n
    a[0], a[1], a[2] = d[0] + reach * p0, d[1] + reach * p1, d[2] + reach * p2
    for r in range(3):
        b[r] = d[r] + reach * lo[r]
    na, nb = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]), np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    if na < 1e-9 or nb < 1e-9:  # a limb folded onto itself: its end has no direction
        return
    for r in range(3):
        a[r] /= na
        b[r] /= nb
    _swing(a, b, sw)
    _mm(sw, g, m)
    g[:, :] = m
    for r in range(3):
        lo[r] = sw[r, 0] * p0 + sw[r, 1] * p1 + sw[r, 2] * p2


# The rig's arrays travel packed in two buffers (part i is buf[at[i]:at[i + 1]]): numba checks each
# argument's type per call, most of a batch-1 call for two dozen arrays.
INT_PARTS = (
    "src_order", "src_par_s", "fixed_par_s", "translated_par_s", "vec_par_s", "vec_nz", "num_plain", "lateral_j",
    "step_i", "bn_parents", "bn_order", "delta_j", "anc_bn_s", "mapped_j", "mapped_s", "mapped_par_s", "drop_par",
)  # fmt: skip
FLOAT_PARTS = (
    "fixed_off", "vec_off", "vec_w", "axes", "m_tgt_t", "step_nat", "step_b", "step_k", "step_m_loc_t", "bn_fixed_q",
    "step_split_nat", "drop_off", "drop_ref", "step_reach",
)  # fmt: skip


def pack(parts: dict, names: tuple[str, ...], dtype) -> tuple[np.ndarray, np.ndarray]:
    """(buffer, offsets) holding `parts[name]` (arrays or scalars) flattened in the order of `names`."""
    flat = [np.asarray(parts[n], dtype=dtype).ravel() for n in names]
    at = np.zeros(len(flat) + 1, dtype=np.int64)
    at[1:] = np.cumsum([len(f) for f in flat])
    return np.ascontiguousarray(np.concatenate(flat), dtype=dtype), at


@njit(cache=True, error_model="numpy", inline="always")
def _part(buf, at, i):
    return buf[at[i] : at[i + 1]]


@njit(cache=True, error_model="numpy", inline="always")
def _part3(buf, at, i):
    return buf[at[i] : at[i + 1]].reshape(-1, 3)


@njit(cache=True, error_model="numpy", inline="always")
def _part33(buf, at, i):
    return buf[at[i] : at[i + 1]].reshape(-1, 3, 3)


# --------------------------------------------------------------------------- the two directions


@njit(cache=True, error_model="numpy")
def _to_model(root, rot, rig, scale, vertical_offset, hinges, fold, hips_out, rot_out):
    """Client frames -> BN Hips translations and rotations (`FrameRetargeter.to_model`). `fold` is a
    bool the caller passes (always True): a literal True would compile `_bn_globals` a second time."""
    nb, base = rig.bn_parents.shape[0], rig.num_plain + 2 * rig.lateral_j.shape[0]
    nv = base + rig.drop_par.shape[0]
    gs = np.empty((rig.src_order.shape[0], 3, 3))
    gb = np.empty((nb, 3, 3))
    terms, raw, vec = np.empty((rig.vec_off.shape[0], 3)), np.empty((nv, 3)), np.empty((nv, 3))
    w33, w3 = np.empty((3, 3, 3)), np.empty((3, 3))
    m, gp = np.empty((3, 3)), np.empty((3, 3))
    c, t, h = np.empty(3), np.empty(3), np.empty(3)
    for f in range(root.shape[0]):
        _source_fk(rot[f], rig.src_order, rig.src_par_s, gs, m)
        _hips_terms(gs, rig.fixed_par_s, rig.fixed_off, rig.translated_par_s, c, gp, t)
        _mv(gp, root[f], t)
        for r in range(3):
            t[r] += c[r]
        _mv(rig.axes, t, h)
        for r in range(3):
            hips_out[f, r] = h[r] * scale
        hips_out[f, 1] += vertical_offset
        _bn_globals(gs, rig, gb, terms, raw, vec, w33, w3, hinges[f if hinges.shape[0] > 1 else 0], fold)
        low = np.inf  # the client's lowest foot point below its hips (`FrameRetargeter._drop`)
        for v in range(base, nv):
            low = min(low, vec[v, 1] - rig.drop_ref[0, v - base])
        hips_out[f, 1] += max(scale * low - _bn_lowest(gb, rig.drop_par, rig.drop_off, rig.drop_ref), 0.0)
        for j in range(nb):
            if rig.bn_fixed_q[j, 3] >= 0.0:  # a leaf (or the static root): its natural local rotation
                for r in range(4):
                    rot_out[f, j, r] = rig.bn_fixed_q[j, r]
            else:
                _local_of(gb, rig.bn_parents[j], j, m, rot_out[f, j])


@njit(cache=True, error_model="numpy")
def _to_source(root_bn, rot_bn, src_rot, rig, scale, vertical_offset, hinges, fold, root_out, rot_out):
    """BN frames and client rotations -> client frames (`FrameRetargeter.to_source`)."""
    nb, ns, base = rig.bn_parents.shape[0], rig.src_order.shape[0], rig.num_plain + 2 * rig.lateral_j.shape[0]
    nv = base + rig.drop_par.shape[0]
    gs = np.empty((ns, 3, 3))
    gbc = np.empty((nb, 3, 3))
    gbn = np.empty((nb, 3, 3))
    delta = np.empty((nb + 1, 3, 3))  # delta[nb]: identity, for joints with no mapped ancestor
    g_new = np.empty((ns, 3, 3))
    terms, raw, vec = np.empty((rig.vec_off.shape[0], 3)), np.empty((nv, 3)), np.empty((nv, 3))
    w33, w3 = np.empty((3, 3, 3)), np.empty((3, 3))
    m, m2, gp = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    c, h, t = np.empty(3), np.empty(3), np.empty(3)
    _eye(delta[nb])
    same_axes = rig.axes[0, 0] == 1.0 and rig.axes[1, 1] == 1.0 and rig.axes[2, 2] == 1.0  # the client's world is BN's
    drop_e = 0  # rig.vec_nz lists its entries row by row: the foot points' rows come last
    while drop_e < rig.vec_nz.shape[0] and rig.vec_nz[drop_e, 0] < base:
        drop_e += 1
    for f in range(root_bn.shape[0]):
        for s in range(rig.bn_order.shape[0]):  # BN world rotations of the given frame, parents first
            j = rig.bn_order[s]
            _world_of(gbn, rig.bn_parents[j], j, rot_bn[f, j], m)
        _source_fk(src_rot[f], rig.src_order, rig.src_par_s, gs, m)
        _bn_globals(gs, rig, gbc, terms, raw, vec, w33, w3, hinges[f if hinges.shape[0] > 1 else 0], fold)
        for i in range(rig.delta_j.shape[0]):  # the change of each BN joint used, in the client's world
            j = rig.delta_j[i]
            if same_axes:
                _mmt(gbn[j], gbc[j], delta[j])
            else:
                _mmt(gbn[j], gbc[j], m)
                _mtm(rig.axes, m, m2)
                _mm(m2, rig.axes, delta[j])
        for s in range(ns):
            _mm(delta[rig.anc_bn_s[s]], gs[s], g_new[s])
        rot_out[f] = src_rot[f]  # unmapped joints keep the client's local rotations
        for i in range(rig.mapped_j.shape[0]):
            _local_of(g_new, rig.mapped_par_s[i], rig.mapped_s[i], m, rot_out[f, rig.mapped_j[i]])
        for v in range(base, nv):  # hips -> foot points of the new client pose (`FrameRetargeter._drop`)
            raw[v, 0], raw[v, 1], raw[v, 2] = 0.0, 0.0, 0.0
        for e in range(drop_e, rig.vec_nz.shape[0]):
            v = rig.vec_nz[e, 0]
            if v >= base:
                tt, w, par = rig.vec_nz[e, 1], rig.vec_w[e], rig.vec_par_s[rig.vec_nz[e, 1]]
                for r in range(3):
                    raw[v, r] += w * (
                        g_new[par, r, 0] * rig.vec_off[tt, 0]
                        + g_new[par, r, 1] * rig.vec_off[tt, 1]
                        + g_new[par, r, 2] * rig.vec_off[tt, 2]
                    )
        low = np.inf
        for v in range(base, nv):
            low = min(
                low,
                rig.axes[1, 0] * raw[v, 0]
                + rig.axes[1, 1] * raw[v, 1]
                + rig.axes[1, 2] * raw[v, 2]
                - rig.drop_ref[0, v - base],
            )
        drop = max(scale * low - _bn_lowest(gbn, rig.drop_par, rig.drop_off, rig.drop_ref), 0.0)
        t[0], t[1], t[2] = (
            root_bn[f, 0] / scale,
            (root_bn[f, 1] - vertical_offset - drop) / scale,
            root_bn[f, 2] / scale,
        )
        for r in range(3):  # rig.axes.T @ t: the client's world
            h[r] = rig.axes[0, r] * t[0] + rig.axes[1, r] * t[1] + rig.axes[2, r] * t[2]
        # the chain above the hips is unchanged
        _hips_terms(gs, rig.fixed_par_s, rig.fixed_off, rig.translated_par_s, c, gp, t)
        for r in range(3):
            h[r] -= c[r]
        for r in range(3):
            root_out[f, r] = gp[0, r] * h[0] + gp[1, r] * h[1] + gp[2, r] * h[2]


@njit(cache=True, error_model="numpy")
def _rig(ints, int_at, floats, float_at):
    """The rig's arrays as a `Rig`, views of the packed buffers (`pack`, `INT_PARTS`, `FLOAT_PARTS`)."""
    i, ia, f, fa = ints, int_at, floats, float_at
    return Rig(
        _part(i, ia, 0), _part(i, ia, 1), _part(i, ia, 2), _part3(f, fa, 0), i[ia[3]],  # slots, the hips' chain
        _part(i, ia, 4), _part3(f, fa, 1), _part(i, ia, 5).reshape(-1, 2), _part(f, fa, 2),  # segment terms
        _part33(f, fa, 3)[0], i[ia[6]], _part33(f, fa, 4), _part(i, ia, 7),  # axes, two-vector joints
        _part(i, ia, 8).reshape(-1, 8), _part33(f, fa, 5), _part3(f, fa, 6), _part3(f, fa, 7),  # other joints' steps
        _part33(f, fa, 8), _part33(f, fa, 10),
        _part(i, ia, 9), _part(f, fa, 9).reshape(-1, 4), _part(i, ia, 10), _part(i, ia, 11),  # BN joints
        _part(i, ia, 12), _part(i, ia, 13), _part(i, ia, 14), _part(i, ia, 15),  # slots' BN joint, mapped joints
        _part(i, ia, 16).reshape(-1, 4), _part(f, fa, 11).reshape(-1, 4, 3), _part(f, fa, 12).reshape(2, -1),  # feet
        _part(f, fa, 13),  # the limbs' reach
    )  # fmt: skip


@njit(cache=True, error_model="numpy")
def to_model(root, rot, ints, int_at, floats, float_at, scale, vertical_offset, hinges, fold, hips_out, rot_out):
    """`_to_model` with the rig's arrays packed (`pack`)."""
    rig = _rig(ints, int_at, floats, float_at)
    _to_model(root, rot, rig, scale, vertical_offset, hinges, fold, hips_out, rot_out)


@njit(cache=True, error_model="numpy")
def to_source(
    root_bn, rot_bn, src_rot, ints, int_at, floats, float_at, scale, vertical_offset, hinges, fold, root_out, rot_out
):
    """`_to_source` with the rig's arrays packed (`pack`)."""
    rig = _rig(ints, int_at, floats, float_at)
    _to_source(root_bn, rot_bn, src_rot, rig, scale, vertical_offset, hinges, fold, root_out, rot_out)
