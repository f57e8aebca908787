"""Compiled kernels (numba) for Style-ERD's per-frame geometry: forward kinematics, the causal
input features and output pose, and the LSTM cell's elementwise passes around the BLAS products
(~100 numpy calls per frame otherwise). Formulas of `features.py` and `models.motion.features`,
which the tests compare with.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..motion.bn_skeleton import HIPS
from ..motion.quaternion import axis_angle, dot3, qdot, qinv, qmul, qneg, quat_at, qunit, qyaw, row3, row4, turn_y, wrap

# --------------------------------------------------------------------------- kernels


@njit(cache=True, error_model="numpy")
def features(rotations, pos, prev_pos, prev_yaw, has_prev, ref, facing, feet, leg, fps):
    """Causal features (N, 216) and facing yaw (N,) of N frames (layout in features.py)."""
    n, J = rotations.shape[0], rotations.shape[1]
    nb = J - 1
    pos_at, vel_at, root_at = 4 * nb, 7 * nb, 10 * nb
    out = np.empty((n, 10 * nb + 6))
    yaws = np.empty(n)
    for f in range(n):
        # facing: forward = cross(left, up) with left = hip and shoulder lines; yaw 0 faces +Z
        hl, hr, sl, sr = facing[0], facing[1], facing[2], facing[3]
        left_x = pos[f, hl, 0] - pos[f, hr, 0] + pos[f, sl, 0] - pos[f, sr, 0]
        left_z = pos[f, hl, 2] - pos[f, hr, 2] + pos[f, sl, 2] - pos[f, sr, 2]
        yaw = math.atan2(-left_z, left_x)
        yaws[f] = yaw
        moving = has_prev[f]
        # rotations: unit, Hips without its yaw, each in the hemisphere of its reference
        unyaw = qyaw(-yaw)
        for b in range(nb):
            q = qunit(quat_at(rotations, f, b + 1))
            if b == 0:
                q = qmul(unyaw, q)
            if qdot(q, row4(ref, b)) < 0.0:
                q = qneg(q)
            out[f, 4 * b], out[f, 4 * b + 1], out[f, 4 * b + 2], out[f, 4 * b + 3] = q
        # positions in the facing frame (origin: Hips on the ground), velocities (backward difference)
        gx, gz = pos[f, HIPS, 0], pos[f, HIPS, 2]
        c, s = math.cos(-yaw), math.sin(-yaw)
        for j in range(1, J):
            p, v = pos_at + 3 * (j - 1), vel_at + 3 * (j - 1)
            out[f, p], out[f, p + 2] = turn_y(pos[f, j, 0] - gx, pos[f, j, 2] - gz, c, s)
            out[f, p + 1] = pos[f, j, 1]
            if moving:
                out[f, v], out[f, v + 2] = turn_y(
                    (pos[f, j, 0] - prev_pos[f, j, 0]) * fps, (pos[f, j, 2] - prev_pos[f, j, 2]) * fps, c, s
                )
                out[f, v + 1] = (pos[f, j, 1] - prev_pos[f, j, 1]) * fps
            else:
                out[f, v], out[f, v + 1], out[f, v + 2] = 0.0, 0.0, 0.0
        out[f, root_at : root_at + 3] = out[f, vel_at : vel_at + 3]  # the Hips' velocity
        out[f, root_at + 3] = wrap(yaw - prev_yaw[f]) * fps if moving else 0.0
        # contacts: ankle or toe low and slow (thresholds scale with the leg length)
        for k in range(2):
            planted = False
            for m in range(2):
                j = feet[k, m]
                height = 0.12 * 1.8 if m == 0 else 0.12
                speed = 0.0
                if moving:
                    vx = (pos[f, j, 0] - prev_pos[f, j, 0]) * fps
                    vy = (pos[f, j, 1] - prev_pos[f, j, 1]) * fps
                    vz = (pos[f, j, 2] - prev_pos[f, j, 2]) * fps
                    speed = math.sqrt(vx * vx + vy * vy + vz * vz)
                planted = planted or (pos[f, j, 1] < height * leg and speed < 0.5 * leg)
            out[f, root_at + 4 + k] = 1.0 if planted else 0.0
    return out, yaws


@njit(cache=True, error_model="numpy")
def output_pose(x, y, yaw, has_prev, prev_root, root, rot_in, fps):
    """Network output y (B, 88) -> (root (B, 3), rotations (B, 22, 4)): input plus offsets, as model.py."""
    B, J = rot_in.shape[0], rot_in.shape[1]
    nb = J - 1
    out_root = np.empty((B, 3))
    out_rot = np.empty((B, J, 4))
    for b in range(B):
        for i in range(4):
            out_rot[b, 0, i] = rot_in[b, 0, i]
        for k in range(nb):
            q = (
                x[b, 4 * k] + y[b, 4 * k],
                x[b, 4 * k + 1] + y[b, 4 * k + 1],
                x[b, 4 * k + 2] + y[b, 4 * k + 2],
                x[b, 4 * k + 3] + y[b, 4 * k + 3],
            )
            norm = max(math.sqrt(qdot(q, q)), 1e-6)
            q = (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
            if k == 0:
                q = qmul(qyaw(yaw[b]), q)
            out_rot[b, k + 1, 0], out_rot[b, k + 1, 1], out_rot[b, k + 1, 2], out_rot[b, k + 1, 3] = q
        v = 10 * nb  # root velocity features; network: 4 * nb rotation offsets, then 3 velocity, then height
        sx, sz = turn_y(x[b, v] + y[b, 4 * nb], x[b, v + 2] + y[b, 4 * nb + 2], math.cos(yaw[b]), math.sin(yaw[b]))
        if has_prev[b]:
            out_root[b, 0], out_root[b, 2] = prev_root[b, 0] + sx / fps, prev_root[b, 2] + sz / fps
        else:
            out_root[b, 0], out_root[b, 2] = root[b, 0], root[b, 2]
        out_root[b, 1] = x[b, 4 * nb + 1] + y[b, 4 * nb + 3]  # Hips height: first position feature's y + offset
    return out_root, out_rot


# --------------------------------------------------------------------------- the LSTM cell around its products
# A layer's elementwise rest in place on the state's layout; numpy's arithmetic, so the same bits.


@njit(cache=True, error_model="numpy")
def lstm_inputs(inp, hs, layer, xin):
    """xin (K, B, 2H) = [inp, hs[:, :, layer] per branch]; hs: the state's (B, K, layers, H)."""
    K, B, H = inp.shape
    for k in range(K):
        for b in range(B):
            for j in range(H):
                xin[k, b, j] = inp[k, b, j]
                xin[k, b, H + j] = hs[b, k, layer, j]
    return xin


@njit(cache=True, error_model="numpy")
def lstm_cell(s, cs, layer, one, new_c, twice_c):
    """c = f c_prev + i (2 s_g - 1) from gate sigmoids s into new_c, and 2c (sigmoid(2c) gives tanh)."""
    K, B, H = twice_c.shape
    for k in range(K):
        for b in range(B):
            for j in range(H):
                g = s[k, b, 2 * H + j]
                c = s[k, b, H + j] * cs[b, k, layer, j] + s[k, b, j] * ((g + g) - one)
                new_c[b, k, layer, j] = c
                twice_c[k, b, j] = c + c
    return twice_c


@njit(cache=True, error_model="numpy")
def lstm_hidden(s, sig_twice_c, layer, one, new_h, out):
    """h = o tanh(c) = s_o (2 sigmoid(2c) - 1) into out (K, B, H) and new_h (B, K, layers, H)."""
    K, B, H = out.shape
    for k in range(K):
        for b in range(B):
            for j in range(H):
                t = sig_twice_c[k, b, j]
                h = s[k, b, 3 * H + j] * ((t + t) - one)
                out[k, b, j] = h
                new_h[b, k, layer, j] = h
    return out


# --------------------------------------------------------------------------- the arms' twist range


@njit(cache=True, error_model="numpy")
def twist_clamp_batch(q, w, joints, axes, mean, lo, hi, out):
    """Listed joints' twists moved into [lo, hi] by the weights: t + sum_s w_s (clip(t_s) - t_s)."""
    out[:] = q
    for b in range(q.shape[0]):
        for k in range(joints.shape[0]):
            j = joints[k]
            axis = row3(axes, k)
            qj = quat_at(q, b, j)
            delta = 0.0
            for s in range(w.shape[1]):
                ws = w[b, s]
                if ws == 0.0:
                    continue
                d = qmul(qinv(quat_at(mean, s, k)), qj)
                t = wrap(2.0 * math.atan2(dot3(d, axis), d[3]))
                delta += ws * (min(max(t, lo[s, k]), hi[s, k]) - t)
            if delta != 0.0:
                o = qmul(qj, axis_angle(axis, delta))
                out[b, j, 0], out[b, j, 1], out[b, j, 2], out[b, j, 3] = o
    return out
