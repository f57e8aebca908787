"""Compiled kernels (numba) for the LTI streaming step: one pass per session over plain arrays.

Why compiled: the vectorised numpy step spent ~1.3 ms per frame at batch 1 in ~950 small numpy
calls of about a microsecond each, while the arithmetic
of a frame is a few thousand multiply-adds. Here the geometry of each session is a loop on
scalars and 4-tuples (quaternions, scalar-last like the rest of the project), so a frame costs a
few microseconds, at batch 1 as well as batched, and the maths reads like the formulas in
`representation.py` (offline, numpy) and the paper.

The LTI product uses each style's [[A, B], [C, D]] in CSR form (the per-joint systems are
combined block-diagonally, so ~95% of the matrix is zeros), applied to all the sessions using
the style at once: each matrix entry is loaded once per frame, not once per session.

Everything is float64; the results equal the numpy formulas to round-off.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from ..motion.bn_skeleton import HIPS, NUM_JOINTS
from ..motion.rotation_ball_kernels import clamp_joint as _clamp_joint

FEATURE_DIM = 67  # root displacement (2), yaw change, height, 21 expmaps

# --------------------------------------------------------------------------- quaternions on 4-tuples


@njit(cache=True, error_model="numpy")
def qmul(a, b):
    """Hamilton product a * b (apply b, then a)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


@njit(cache=True, error_model="numpy")
def qinv(q):
    return (-q[0], -q[1], -q[2], q[3])


@njit(cache=True, error_model="numpy")
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True, error_model="numpy")
def dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, error_model="numpy")
def qrot(q, v):
    """Rotate vector v by unit quaternion q."""
    xyz = (q[0], q[1], q[2])
    t = cross(xyz, v)
    t = (2.0 * t[0], 2.0 * t[1], 2.0 * t[2])
    u = cross(xyz, t)
    w = q[3]
    return (v[0] + w * t[0] + u[0], v[1] + w * t[1] + u[1], v[2] + w * t[2] + u[2])


@njit(cache=True, error_model="numpy")
def quat_at(a, i, j):
    """Quaternion a[i, j] of a (..., ..., 4) array as a 4-tuple."""
    return (a[i, j, 0], a[i, j, 1], a[i, j, 2], a[i, j, 3])


@njit(cache=True, error_model="numpy")
def row4(a, j):
    return (a[j, 0], a[j, 1], a[j, 2], a[j, 3])


@njit(cache=True, error_model="numpy")
def quat_to_rotvec(q):
    """Exponential map, angle in [0, pi] (the w >= 0 branch); see representation.quat_to_rotvec."""
    w = abs(q[3])
    sign = 1.0 if q[3] + 1e-300 >= 0.0 else -1.0
    v = (q[0] * sign, q[1] * sign, q[2] * sign)
    s = math.sqrt(dot3(v, v))
    scale = 2.0 * math.atan2(s, w) / s if s > 1e-8 else 2.0 / max(w, 1e-12)
    return (v[0] * scale, v[1] * scale, v[2] * scale)


@njit(cache=True, error_model="numpy")
def rotvec_to_quat(r):
    angle = math.sqrt(dot3(r, r))
    scale = 0.5 - angle * angle / 48.0 if angle < 1e-8 else math.sin(0.5 * angle) / angle
    return (r[0] * scale, r[1] * scale, r[2] * scale, math.cos(0.5 * angle))


@njit(cache=True, error_model="numpy")
def split_hips(q):
    """q_hips = qyaw(yaw) * tilt -> (yaw, tilt); see representation.split_hips."""
    x, y, z, w = q
    yaw = math.atan2(2.0 * (y * z + w * x), -2.0 * (x * y - w * z))
    c, s = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return yaw, (c * x - s * z, c * y - s * w, c * z + s * x, c * w + s * y)


@njit(cache=True, error_model="numpy")
def qyaw(yaw):
    return (0.0, math.sin(0.5 * yaw), 0.0, math.cos(0.5 * yaw))


@njit(cache=True, error_model="numpy")
def rotate_y(x, z, yaw):
    """Ground-plane vector (x, z) turned by yaw about +Y."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * x + s * z, -s * x + c * z


@njit(cache=True, error_model="numpy")
def wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# --------------------------------------------------------------------------- styles, packed


class PackedStyles(NamedTuple):
    """Every style translator's constants concatenated over the model's current styles, in order,
    so the step kernel takes a fixed set of arrays whatever the style set is. Style s owns state
    entries x[x_off[s]:x_off[s+1]] and rows row_off[s]:row_off[s+1] of the stacked CSR matrices
    M_s = [[A, B], [C, D]] (columns local to the style: its state, then the 67 inputs)."""

    x_off: np.ndarray  # (S + 1,) int64
    row_off: np.ndarray  # (S + 1,) int64
    indptr: np.ndarray  # (rows + 1,) int64, into indices/data
    indices: np.ndarray  # (nnz,) int32 (half the memory traffic of int64)
    data: np.ndarray  # (nnz,)
    in_mean: np.ndarray  # (S, 67)
    in_std: np.ndarray  # (S, 67)
    in_lo: np.ndarray  # (S, 67) training range of the normalised input (erf blend)
    in_hi: np.ndarray  # (S, 67)
    out_mean: np.ndarray  # (S, 68)
    out_std: np.ndarray  # (S, 68)
    k: np.ndarray  # (S, 2) erf blend k_p, k_c
    ref: np.ndarray  # (S, 22, 4) per-joint reference rotations
    fp_w: np.ndarray  # (2, N) footplant projection per foot, columns aligned with the state
    fp_mean: np.ndarray  # (S, 2, 2) per foot, per class (free, planted)
    fp_var: np.ndarray  # (S, 2, 2)
    fp_prior: np.ndarray  # (S, 2, 2) log prior
    has_fp: np.ndarray  # (S,) bool
    prior_mean: np.ndarray  # (S, 22, 4) rotation prior (prior.py): per joint, the real style's mean rotation
    prior_radii: np.ndarray  # (S, 2, 22) inner, outer radius (radians; inf: no prior)


def pack_styles(translators: list) -> PackedStyles:
    """PackedStyles of `StyleTranslator`s (in style order); done once per style-set change."""
    from scipy import sparse

    x_off, row_off, indptr, indices, data = [0], [0], [], [], []
    fp_w, fp_mean, fp_var, fp_prior, has_fp = [], [], [], [], []
    prior_mean, prior_radii = [], []
    nnz = 0
    for tr in translators:
        M = sparse.csr_matrix(tr.M)
        indptr.append(M.indptr[:-1] + nnz)
        indices.append(M.indices)
        data.append(M.data)
        nnz += M.nnz
        x_off.append(x_off[-1] + tr.n)
        row_off.append(row_off[-1] + M.shape[0])
        fp = tr.footplant
        has_fp.append(fp is not None)
        fp_w.append(fp.w if fp is not None else np.zeros((tr.n, 2)))
        fp_mean.append(fp.mean if fp is not None else np.zeros((2, 2)))
        fp_var.append(fp.var if fp is not None else np.ones((2, 2)))
        fp_prior.append(fp.log_prior if fp is not None else np.zeros((2, 2)))
        mean, radii = tr.ball()
        prior_mean.append(mean)
        prior_radii.append(radii)
    indptr.append(np.array([nnz]))
    f64 = lambda parts: np.ascontiguousarray(np.stack(parts), dtype=np.float64)
    return PackedStyles(
        np.array(x_off, np.int64),
        np.array(row_off, np.int64),
        np.concatenate(indptr).astype(np.int64),
        np.concatenate(indices).astype(np.int32),
        np.concatenate(data).astype(np.float64),
        f64([tr.in_mean for tr in translators]),
        f64([tr.in_std for tr in translators]),
        f64([tr.in_lo for tr in translators]),
        f64([tr.in_hi for tr in translators]),
        f64([tr.out_mean for tr in translators]),
        f64([tr.out_std for tr in translators]),
        f64([(tr.k_p, tr.k_c) for tr in translators]),
        f64([tr.ref for tr in translators]),
        np.ascontiguousarray(np.concatenate(fp_w).T, dtype=np.float64),
        f64(fp_mean),
        f64(fp_var),
        f64(fp_prior),
        np.array(has_fp, np.bool_),
        f64(prior_mean),
        f64(prior_radii),
    )


# --------------------------------------------------------------------------- the step


def new_workspace(batch: int, packed: PackedStyles) -> tuple[np.ndarray, ...]:
    """Scratch arrays of `lti_step` for up to `batch` sessions: per session (yaw, yaw-free hips,
    root displacement and yaw change, the input's share, the weight total, root features, contact
    votes), each style's body rotations, and per style its sessions, their erf weights, [x; u],
    M [x; u], the raw features, one output row. Kept between steps: at batch 256 they are ~2 MB,
    and fresh allocations that size cost more in page faults than the step's arithmetic."""
    styles = len(packed.x_off) - 1
    rows = int(np.diff(packed.x_off).max()) + FEATURE_DIM
    return (
        np.empty((batch, 16)),
        np.empty((batch, styles, NUM_JOINTS, 4)),
        np.empty(batch, np.int64),
        np.empty(batch),
        np.empty((rows, batch)),
        np.empty((rows, batch)),
        np.empty((FEATURE_DIM, batch)),
        np.empty(FEATURE_DIM),
    )


@njit(cache=True, error_model="numpy")
def _planted(x, fp_w, row0, mean, var, log_prior, foot):
    """Footplant class of one foot: the more likely Gaussian class (free, planted) of the state
    projected on the foot's discriminant (FootplantClassifier.predict)."""
    proj = 0.0
    for i in range(x.shape[0]):
        proj += x[i] * fp_w[foot, row0 + i]
    ll_free = -0.5 * (proj - mean[foot, 0]) ** 2 / var[foot, 0] - 0.5 * math.log(var[foot, 0]) + log_prior[foot, 0]
    ll_planted = -0.5 * (proj - mean[foot, 1]) ** 2 / var[foot, 1] - 0.5 * math.log(var[foot, 1]) + log_prior[foot, 1]
    return ll_planted > ll_free


@njit(cache=True, error_model="numpy")
def _style_inputs(s, root_y, rotations, yaw_tilt, delta, x_in, P, blend, zin, feats, col):
    """One session's input to style s's LTI system, into column `col` of zin (the style's state,
    then the normalised features; representation.pose_features / sequence_features) and of
    feats (the raw features). Returns the erf generalisation blend weight."""
    (
        x_off,
        row_off,
        indptr,
        indices,
        data,
        in_mean,
        in_std,
        in_lo,
        in_hi,
        out_mean,
        out_std,
        k,
        ref,
        fp_w,
        fp_mean,
        fp_var,
        fp_prior,
        has_fp,
        prior_mean,
        prior_radii,
    ) = P
    n = x_in.shape[0]
    feats[0, col], feats[1, col], feats[2, col], feats[3, col] = delta[0], delta[1], delta[2], root_y
    for j in range(1, NUM_JOINTS):
        q = yaw_tilt if j == HIPS else row4(rotations, j)
        r = quat_to_rotvec(qmul(qinv(quat_at(ref, s, j)), q))
        feats[3 * j + 1, col], feats[3 * j + 2, col], feats[3 * j + 3, col] = r
    for i in range(n):
        zin[i, col] = x_in[i]
    blend_w = 0.0
    for d in range(FEATURE_DIM):
        u = (feats[d, col] - in_mean[s, d]) / in_std[s, d]
        zin[n + d, col] = u
        if blend:  # max over DOFs of erf(max(0, dist - k_p) / k_c)
            beyond = max(u - in_hi[s, d], in_lo[s, d] - u) - k[s, 0]
            if beyond > 0.0:  # erf(0) = 0 inside the training range: most DOFs, most frames
                blend_w = max(blend_w, math.erf(beyond / k[s, 1]))
    return blend_w


@njit(cache=True, error_model="numpy")
def _style_outputs(s, w, z, feats, col, blend_w, x_out, P, keep_heading, root_feats, quats, out):
    """Style s's result for one session from column `col` of z = M [x; u]: the new state into
    x_out, w * (root displacement, yaw change, height) added to root_feats, the body rotations
    (22, 4) into quats. Returns the footplant contacts (left, right). out: scratch (67,)."""
    (
        x_off,
        row_off,
        indptr,
        indices,
        data,
        in_mean,
        in_std,
        in_lo,
        in_hi,
        out_mean,
        out_std,
        k,
        ref,
        fp_w,
        fp_mean,
        fp_var,
        fp_prior,
        has_fp,
        prior_mean,
        prior_radii,
    ) = P
    n = x_out.shape[0]
    for i in range(n):
        x_out[i] = z[i, col]
    for d in range(FEATURE_DIM):  # the log time warp (last output) is not used online
        y = z[n + d, col] * out_std[s, d] + out_mean[s, d]
        out[d] = (1.0 - blend_w) * y + blend_w * feats[d, col]
    if keep_heading:
        out[2] = feats[2, col]
    for d in range(4):
        root_feats[d] += w * out[d]
    # body rotations (representation.static_to_rotations with yaw 0)
    quats[0, 0], quats[0, 1], quats[0, 2], quats[0, 3] = 0.0, 0.0, 0.0, 1.0
    for j in range(1, NUM_JOINTS):
        q = qmul(quat_at(ref, s, j), rotvec_to_quat((out[3 * j + 1], out[3 * j + 2], out[3 * j + 3])))
        q = _clamp_joint(q, quat_at(prior_mean, s, j), prior_radii[s, 0, j], prior_radii[s, 1, j], j == HIPS)
        quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3] = q
    if not has_fp[s]:
        return False, False
    return _planted(x_out, fp_w, x_off[s], fp_mean[s], fp_var[s], fp_prior[s], 0), _planted(
        x_out, fp_w, x_off[s], fp_mean[s], fp_var[s], fp_prior[s], 1
    )


@njit(cache=True, error_model="numpy")
def _sparse_product(indptr, indices, data, zin, z, m):
    """z[:, :m] = M @ zin[:, :m] for the CSR matrix M (indptr, indices, data). Several sessions:
    each matrix entry is loaded once and applied to all of them (an inner loop over sessions that
    the compiler vectorises); one session: a plain dot product per row (the vectorised loop's
    set-up would cost more than the work). Either way each sum adds the same terms in the same order."""
    for r in range(indptr.shape[0] - 1):
        if m == 1:
            acc = 0.0
            for p in range(indptr[r], indptr[r + 1]):
                acc += data[p] * zin[indices[p], 0]
            z[r, 0] = acc
            continue
        for c in range(m):
            z[r, c] = 0.0
        for p in range(indptr[r], indptr[r + 1]):
            coef, col = data[p], indices[p]
            for c in range(m):
                z[r, c] += coef * zin[col, c]


@njit(cache=True, error_model="numpy")
def lti_step(
    root,
    rotations,
    weights,
    started,
    in_yaw,
    in_ground,
    out_yaw,
    out_ground,
    x,
    out_root,
    out_rot,
    contacts,
    n_yaw,
    n_ground,
    n_out_yaw,
    n_out_ground,
    n_x,
    per_session,
    quats,
    rows,
    blend_w,
    zin,
    z,
    feats,
    out,
    blend,
    keep_heading,
    x_off,
    row_off,
    indptr,
    indices,
    data,
    in_mean,
    in_std,
    in_lo,
    in_hi,
    out_mean,
    out_std,
    k,
    ref,
    fp_w,
    fp_mean,
    fp_var,
    fp_prior,
    has_fp,
    prior_mean,
    prior_radii,
):
    """One streaming frame for B sessions (see model.LTIStyleModel for the state and the style
    mixing). Reads the frame, the weights and the state (started ... x); fills the outputs
    (out_root ... n_x, allocated by the caller: returning arrays from numba costs ~1 us each);
    per_session ... out are scratch (`new_workspace`) for at least B sessions, kept by the caller
    between calls. Arrays are passed one by one (the scratch, the `PackedStyles` fields) because
    numba checks the types of top-level arrays much faster than those inside a tuple.

    Three passes: per session, the input's root transform and its share of the output; per
    style, the LTI step of all sessions using it as one sparse product (each matrix entry is
    loaded once and applied to every session, a loop the compiler vectorises); per session, the
    blend of the styles and the output path. The feet are planted after it (`models.motion.feet`)."""
    P = (
        x_off,
        row_off,
        indptr,
        indices,
        data,
        in_mean,
        in_std,
        in_lo,
        in_hi,
        out_mean,
        out_std,
        k,
        ref,
        fp_w,
        fp_mean,
        fp_var,
        fp_prior,
        has_fp,
        prior_mean,
        prior_radii,
    )
    B, S = weights.shape
    yaws, tilts, deltas, rests = per_session[:, 0], per_session[:, 1:5], per_session[:, 5:8], per_session[:, 8]
    totals, root_feats, votes = per_session[:, 9], per_session[:, 10:14], per_session[:, 14:16]
    for b in range(B):
        for i in range(n_x.shape[1]):
            n_x[b, i] = 0.0  # inactive styles rest at their initial state x = 0
        for leg in range(2):
            contacts[b, leg] = False
        yaw, tilt = split_hips(quat_at(rotations, b, HIPS))
        yaws[b], votes[b, 0], votes[b, 1] = yaw, 0.0, 0.0
        tilts[b, 0], tilts[b, 1], tilts[b, 2], tilts[b, 3] = tilt
        gx, gz = root[b, 0], root[b, 2]
        p_yaw = in_yaw[b] if started[b] else yaw
        dx, dz = rotate_y(
            gx - (in_ground[b, 0] if started[b] else gx), gz - (in_ground[b, 1] if started[b] else gz), -p_yaw
        )
        deltas[b, 0], deltas[b, 1], deltas[b, 2] = dx, dz, wrap(yaw - p_yaw)
        total = 0.0
        for s in range(S):
            total += weights[b, s]
        totals[b] = total
        rests[b] = max(1.0 - total, 0.0)  # share of the input passing through
        for d in range(3):
            root_feats[b, d] = rests[b] * deltas[b, d]
        root_feats[b, 3] = rests[b] * root[b, 1]
    for s in range(S):
        m = 0
        for b in range(B):
            if weights[b, s] > 0.0:
                rows[m] = b
                m += 1
        if m == 0:
            continue
        n = x_off[s + 1] - x_off[s]
        for c in range(m):
            b = rows[c]
            blend_w[c] = _style_inputs(
                s,
                root[b, 1],
                rotations[b],
                row4(tilts, b),
                deltas[b],
                x[b, x_off[s] : x_off[s + 1]],
                P,
                blend,
                zin,
                feats,
                c,
            )
        # [x'; y] = M [x; u] for the m sessions; rows: the state, then the outputs (not the log time warp)
        _sparse_product(indptr[row_off[s] : row_off[s] + n + FEATURE_DIM + 1], indices, data, zin, z, m)
        for c in range(m):
            b = rows[c]
            w = weights[b, s]
            planted = _style_outputs(
                s,
                w,
                z,
                feats,
                c,
                blend_w[c],
                n_x[b, x_off[s] : x_off[s + 1]],
                P,
                keep_heading,
                root_feats[b],
                quats[b, s],
                out,
            )
            votes[b, 0] += w * planted[0]
            votes[b, 1] += w * planted[1]
    for b in range(B):
        fresh = not started[b]
        yaw, rest, rf = yaws[b], rests[b], root_feats[b]
        base, base_w = -1, rest  # the heaviest part (first on ties): the sign reference of the blend
        for s in range(S):
            if weights[b, s] > base_w:
                base, base_w = s, weights[b, s]
        # blend the body: input (with the yaw-free hips) and each style, signs aligned to the base part
        out_rot[b, 0, 0], out_rot[b, 0, 1], out_rot[b, 0, 2], out_rot[b, 0, 3] = 0.0, 0.0, 0.0, 1.0
        for j in range(1, NUM_JOINTS):
            q_in = row4(tilts, b) if j == HIPS else quat_at(rotations, b, j)
            q_base = q_in if base < 0 else quat_at(quats[b], base, j)
            acc = (0.0, 0.0, 0.0, 0.0)
            if rest > 0.0:
                acc = _add_signed(acc, rest, q_in, q_base)
            for s in range(S):
                if weights[b, s] > 0.0:
                    acc = _add_signed(acc, weights[b, s], quat_at(quats[b], s, j), q_base)
            norm = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2] + acc[3] * acc[3])
            q = (acc[0] / norm, acc[1] / norm, acc[2] / norm, acc[3] / norm)
            if j == HIPS:
                q = qmul(qyaw(yaw if fresh else out_yaw[b] + rf[2]), q)
            out_rot[b, j, 0], out_rot[b, j, 1], out_rot[b, j, 2], out_rot[b, j, 3] = q
        # integrate the output path: the first frame starts where the input is
        gx, gz = root[b, 0], root[b, 2]
        if fresh:
            n_out_yaw[b], n_out_ground[b, 0], n_out_ground[b, 1] = yaw, gx, gz
        else:
            sx, sz = rotate_y(rf[0], rf[1], out_yaw[b])
            n_out_yaw[b] = out_yaw[b] + rf[2]
            n_out_ground[b, 0], n_out_ground[b, 1] = out_ground[b, 0] + sx, out_ground[b, 1] + sz
        out_root[b, 0], out_root[b, 1], out_root[b, 2] = n_out_ground[b, 0], rf[3], n_out_ground[b, 1]
        n_yaw[b], n_ground[b, 0], n_ground[b, 1] = yaw, gx, gz
        if totals[b] > 0.0:
            limit = 0.5 * max(totals[b], 1e-12)
            contacts[b, 0], contacts[b, 1] = votes[b, 0] > limit, votes[b, 1] > limit


@njit(cache=True, error_model="numpy")
def _add_signed(acc, w, q, ref):
    """acc + w * q, with q's sign flipped when it points away from ref (q and -q are one rotation)."""
    sign = -w if q[0] * ref[0] + q[1] * ref[1] + q[2] * ref[2] + q[3] * ref[3] < 0.0 else w
    return (acc[0] + sign * q[0], acc[1] + sign * q[1], acc[2] + sign * q[2], acc[3] + sign * q[3])
