"""Compiled kernels (numba) for the LPN-FiLM streaming step: the per-session geometry around the
network and its per-row maths, as loops over scalars instead of the reference's hundreds of small
numpy calls (`tests/reference/lpn_step.py`). The three big matrix products stay BLAS. Formulas of
`features.py`; float64 inside, float32 state and outputs.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from ..motion.kinematics_kernels import world_pose
from ..motion.quaternion import matrix_quat, turn_y, wrap
from . import features as lf

STEP, PAST, FUTURE, SAMPLES = lf.STEP, lf.PAST, lf.FUTURE, lf.SAMPLES  # trajectory sampling
TRAJ_CH, TRAJ_OUT_CH = lf.TRAJ_CH, lf.TRAJ_OUT_CH  # position xz, direction xz, velocity xz (, gait)
NUM_BONES, POSE_CH = lf.NUM_BONES, lf.POSE_CH  # phase bones, pose channels per body joint
# output layout: future trajectory, pose, root delta, phases, frequencies, contacts
Y_TRAJ, Y_POSE, Y_DELTA = lf.TRAJ_OUT.start, lf.POSE_OUT.start, lf.DELTA_OUT.start
Y_PHASE, Y_FREQ, Y_CONTACT = lf.PHASE_OUT.start, lf.FREQ_OUT.start, lf.CONTACT_OUT.start


class Track(NamedTuple):
    """B sessions' trajectory, phases and pose: state entries, read and updated in place."""

    yaw: np.ndarray  # (B,)
    hist_pos: np.ndarray  # (B, H, 2) world xz, the last row the current frame
    hist_dir: np.ndarray  # (B, H, 2)
    hist_vel: np.ndarray  # (B, H, 2)
    hist_gait: np.ndarray  # (B, H)
    hist_phase: np.ndarray  # (B, H, NUM_BONES, 2)
    fut_pos: np.ndarray  # (B, FUTURE, 2) the network's last future prediction, world
    fut_dir: np.ndarray  # (B, FUTURE, 2)
    fut_vel: np.ndarray  # (B, FUTURE, 2)
    fut_phase: np.ndarray  # (B, FUTURE, NUM_BONES, 2)
    pose: np.ndarray  # (B, NB, POSE_CH) in its character frame


class Tracker(NamedTuple):
    """B sessions' input tracker: the state entries of the same names, updated in place."""

    frame: np.ndarray  # (B,) frames stepped so far
    in_pos: np.ndarray  # (B, 2) the input's last Hips xz
    in_vel: np.ndarray  # (B, 2) its smoothed Hips velocity
    lead: np.ndarray  # (B,) cm the character has walked beyond the input while the input was slow


class Body(NamedTuple):
    parents: np.ndarray  # (J,)
    offsets: np.ndarray  # (J, 3)
    facing: np.ndarray  # (4,) left and right hip and shoulder joints (`facing_yaw`)
    fps: float


class Rules(NamedTuple):
    """The runtime's constants around the network (`runtime.py` says what each is for)."""

    smooth: float  # per-frame smoothing of the input's velocity
    run_speed: float
    stop_speed: float
    root_hold: float
    phase_damp: float
    phase_blend: float
    contact_threshold: float
    catch_up: float  # seconds over which derived control makes up the character's lead (0: it never slows for it)
    crawl_speed: float  # input speeds (cm/s) from which derived control is slowed fully ...
    walk_speed: float  # ... to those from which it is not


# --------------------------------------------------------------------------- small maths on scalars and tuples


@njit(cache=True, error_model="numpy")
def elu(v):
    return v if v > 0.0 else math.expm1(v)


# --------------------------------------------------------------------------- kinematics


@njit(cache=True, error_model="numpy")
def facing_yaw(gpos, facing):
    """Facing yaw of world positions (J, 3): forward = left x up, left from the hip and shoulder lines."""
    hl, hr, sl, sr = facing[0], facing[1], facing[2], facing[3]
    left_x = gpos[hl, 0] - gpos[hr, 0] + gpos[sl, 0] - gpos[sr, 0]
    left_z = gpos[hl, 2] - gpos[hr, 2] + gpos[sl, 2] - gpos[sr, 2]
    return math.atan2(-left_z, left_x)


# --------------------------------------------------------------------------- step: before the network


@njit(cache=True, error_model="numpy")
def control_rows(control, given, root, rotations, tracker, walked, body, rules):
    """(B, 4) control (forward, side in cm/s, yaw, gait): given rows as they are, others from the input's
    smoothed Hips velocity (the tracker advances for all, so modes switch smoothly). Below the training
    walks' speeds the network outpaces the input, so a derived velocity is slowed by its lead."""
    frame, in_pos, in_vel, lead = tracker
    parents, offsets, facing, fps = body
    smooth, run_speed, catch_up = rules.smooth, rules.run_speed, rules.catch_up
    forget = math.exp(-1.0 / (fps * catch_up)) if catch_up > 0.0 else 0.0
    B, J = rotations.shape[0], rotations.shape[1]
    out = np.empty((B, 4), np.float32)
    grot, gpos = np.empty((J, 4)), np.empty((J, 3))
    for b in range(B):
        x, z = root[b, 0], root[b, 2]
        vx, vz = 0.0, 0.0
        if frame[b] > 0:
            vx, vz = (x - in_pos[b, 0]) * fps, (z - in_pos[b, 1]) * fps
        in_vel[b, 0] += smooth * (vx - in_vel[b, 0])
        in_vel[b, 1] += smooth * (vz - in_vel[b, 1])
        in_pos[b, 0], in_pos[b, 1] = x, z
        if given[b]:
            out[b, 0], out[b, 1], out[b, 2], out[b, 3] = (
                control[b, 0] * 100.0,
                control[b, 1] * 100.0,
                control[b, 2],
                control[b, 3],
            )
            lead[b] = 0.0  # a client's control owes the input nothing
            continue
        world_pose(root[b], rotations[b], parents, offsets, grot, gpos)
        yaw = facing_yaw(gpos, facing)
        c, s = math.cos(yaw), math.sin(yaw)  # turn_y(.., c, -s): world -> character frame
        speed = math.sqrt(in_vel[b, 0] * in_vel[b, 0] + in_vel[b, 1] * in_vel[b, 1])
        lx, lz = turn_y(in_vel[b, 0], in_vel[b, 1], c, -s)
        out[b, 3] = 1.0 if speed > run_speed else 0.0
        if catch_up > 0.0:
            # only below the training walks' speeds: faster, the network keeps the input's pace (or its style's)
            slow = min(max((rules.walk_speed - speed) / (rules.walk_speed - rules.crawl_speed), 0.0), 1.0)
            ahead = lead[b] + slow * (walked[b] - math.sqrt(vx * vx + vz * vz) / fps)
            lead[b] = ahead if ahead > 0.0 else ahead * forget
            k = 1.0 - slow * min(max(lead[b] / (catch_up * max(speed, 1e-9)), 0.0), 1.0)
            lx, lz = turn_y(k * in_vel[b, 0], k * in_vel[b, 1], c, -s)
        out[b, 0], out[b, 1], out[b, 2] = lz, lx, yaw
    return out


@njit(cache=True, error_model="numpy")
def network_inputs(control, track, fps, bias, x, g):
    """Network input x (B, 343) and gating input g (B, 104); the future (in place) blended toward control."""
    yaw, hist_pos, hist_dir, hist_vel, hist_gait, hist_phase, fut_pos, fut_dir, fut_vel, fut_phase, pose = track
    B, H = hist_pos.shape[0], hist_pos.shape[1]
    for b in range(B):
        yw = float(yaw[b])
        px, pz = hist_pos[b, H - 1, 0], hist_pos[b, H - 1, 1]
        want = control[b, 2]
        wx, wz = turn_y(control[b, 1], control[b, 0], math.cos(want), math.sin(want))  # (side, forward) -> world
        turn = wrap(want - yw)
        for k in range(FUTURE):
            f = (k + 1) / FUTURE
            tau = (k + 1) * STEP / fps
            beta = 1.0 - (1.0 - f) ** bias
            fut_pos[b, k, 0] += beta * (px + wx * tau - fut_pos[b, k, 0])
            fut_pos[b, k, 1] += beta * (pz + wz * tau - fut_pos[b, k, 1])
            a = yw + turn * f
            dx = fut_dir[b, k, 0] + beta * (math.sin(a) - fut_dir[b, k, 0])
            dz = fut_dir[b, k, 1] + beta * (math.cos(a) - fut_dir[b, k, 1])
            n = math.sqrt(max(dx * dx + dz * dz, 1e-16))
            fut_dir[b, k, 0], fut_dir[b, k, 1] = dx / n, dz / n
            fut_vel[b, k, 0] += beta * (wx - fut_vel[b, k, 0])
            fut_vel[b, k, 1] += beta * (wz - fut_vel[b, k, 1])
        c, s = math.cos(yw), math.sin(yw)  # turn_y(.., c, -s): world -> character frame
        for i in range(SAMPLES):
            o = i * TRAJ_CH
            if i <= PAST:
                r = i * STEP
                p, d, v, gait = hist_pos[b, r], hist_dir[b, r], hist_vel[b, r], hist_gait[b, r]
            else:
                k = i - PAST - 1
                p, d, v, gait = fut_pos[b, k], fut_dir[b, k], fut_vel[b, k], control[b, 3]
            x[b, o], x[b, o + 1] = turn_y(p[0] - px, p[1] - pz, c, -s)
            x[b, o + 2], x[b, o + 3] = turn_y(d[0], d[1], c, -s)
            x[b, o + 4], x[b, o + 5] = turn_y(v[0], v[1], c, -s)
            x[b, o + 6] = gait
        o = SAMPLES * TRAJ_CH
        for j in range(pose.shape[1]):
            for ch in range(pose.shape[2]):
                x[b, o] = pose[b, j, ch]
                o += 1
        o = 0
        for i in range(SAMPLES):
            ph = hist_phase[b, i * STEP] if i <= PAST else fut_phase[b, i - PAST - 1]
            for bone in range(NUM_BONES):
                g[b, o], g[b, o + 1] = ph[bone, 0], ph[bone, 1]
                o += 2


# --------------------------------------------------------------------------- the network's per-row maths


@njit(cache=True, error_model="numpy")
def elu_dense(h, w, b, out):
    """out = b + ELU(h) @ w for one row (w as (in, out)): a hidden layer of the gating MLP."""
    for j in range(out.shape[0]):
        out[j] = b[j]
    for i in range(h.shape[0]):
        hi = elu(h[i])
        for j in range(out.shape[0]):
            out[j] += hi * w[i, j]


@njit(cache=True, error_model="numpy")
def gating(g, scale, layers):
    """Expert blend (B, E): softmax of the gating MLP (two ELU layers) on g / scale."""
    (w0, b0), (w1, b1), (w2, b2) = layers
    B = g.shape[0]
    n0, n1, E = w0.shape[1], w1.shape[1], w2.shape[1]
    alpha = np.empty((B, E), np.float32)
    h0, h1, h2 = np.empty(n0), np.empty(n1), np.empty(E)
    for b in range(B):
        for j in range(n0):
            h0[j] = b0[j]
        for i in range(w0.shape[0]):
            gi = g[b, i] / scale
            for j in range(n0):
                h0[j] += gi * w0[i, j]
        elu_dense(h0, w1, b1, h1)
        elu_dense(h1, w2, b2, h2)
        top = -math.inf
        for j in range(E):
            top = max(top, h2[j])
        total = 0.0
        for e in range(E):
            h2[e] = math.exp(h2[e] - top)
            total += h2[e]
        for e in range(E):
            alpha[b, e] = h2[e] / total
    return alpha


@njit(cache=True, error_model="numpy")
def blend_experts(hw, alpha, bias, b, out):
    """out (n,) = sum_e alpha[b, e] (hw[b, e*n:(e+1)*n] + bias[e]): session b's expert layer."""
    E, n = bias.shape[0], bias.shape[1]
    for o in range(n):
        out[o] = 0.0
    for e in range(E):
        a = float(alpha[b, e])
        for o in range(n):
            out[o] += a * (hw[b, e * n + o] + bias[e, o])


@njit(cache=True, error_model="numpy")
def hidden_layer(hw, alpha, bias, film, layer, out):
    """A hidden layer (B, n): experts blended, layer norm, FiLM h (1 + gamma) + beta, ELU."""
    B, n = hw.shape[0], bias.shape[1]
    h = np.empty(n)
    for b in range(B):
        blend_experts(hw, alpha, bias, b, h)
        mean = 0.0
        for o in range(n):
            mean += h[o]
        mean /= n
        var = 0.0
        for o in range(n):
            var += (h[o] - mean) ** 2
        inv = 1.0 / math.sqrt(var / n + 1e-5)
        for o in range(n):
            out[b, o] = elu((h[o] - mean) * inv * (1.0 + film[b, 2 * layer, o]) + film[b, 2 * layer + 1, o])


@njit(cache=True, error_model="numpy")
def output_layer(hw, alpha, bias, y_mean, y_std):
    """The denormalised network output (B, n) from the last layer's experts' outputs hw (B, E*n)."""
    B, n = hw.shape[0], bias.shape[1]
    y = np.empty((B, n), np.float32)
    h = np.empty(n)
    for b in range(B):
        blend_experts(hw, alpha, bias, b, h)
        for o in range(n):
            y[b, o] = h[o] * y_std[o] + y_mean[o]
    return y


# --------------------------------------------------------------------------- step: after the network


@njit(cache=True, error_model="numpy")
def _shift_history(track, b):
    """Session b's history rows moved up by one (the last row is then free)."""
    hist_pos, hist_dir, hist_vel = track.hist_pos, track.hist_dir, track.hist_vel
    hist_gait, hist_phase = track.hist_gait, track.hist_phase
    for r in range(hist_pos.shape[1] - 1):
        for i in range(2):
            hist_pos[b, r, i], hist_dir[b, r, i], hist_vel[b, r, i] = (
                hist_pos[b, r + 1, i],
                hist_dir[b, r + 1, i],
                hist_vel[b, r + 1, i],
            )
        hist_gait[b, r] = hist_gait[b, r + 1]
        for bone in range(NUM_BONES):
            hist_phase[b, r, bone, 0], hist_phase[b, r, bone, 1] = (
                hist_phase[b, r + 1, bone, 0],
                hist_phase[b, r + 1, bone, 1],
            )


@njit(cache=True, error_model="numpy")
def _local_rotations(y, parents, nc, ns, R, local, out):
    """Local rotations (J, 4) from an output row's predicted forward and up axes. R, local: scratch."""
    for r in range(3):
        for col in range(3):
            R[0, r, col] = 1.0 if r == col else 0.0
    for j in range(1, parents.shape[0]):
        o = Y_POSE + (j - 1) * POSE_CH
        fx, fy, fz = y[o + 6], y[o + 7], y[o + 8]
        n = math.sqrt(max(fx * fx + fy * fy + fz * fz, 1e-18))
        zx, zy, zz = fx / n, fy / n, fz / n
        ux, uy, uz = y[o + 9], y[o + 10], y[o + 11]
        along = ux * zx + uy * zy + uz * zz
        ux, uy, uz = ux - along * zx, uy - along * zy, uz - along * zz
        n = math.sqrt(max(ux * ux + uy * uy + uz * uz, 1e-18))
        ux, uy, uz = ux / n, uy / n, uz / n
        xx, xy, xz = uy * zz - uz * zy, uz * zx - ux * zz, ux * zy - uy * zx  # up x forward
        # columns (x, y, z) in the character frame, then turned about +Y by the new yaw
        R[j, 0, 0], R[j, 1, 0], R[j, 2, 0] = nc * xx + ns * xz, xy, -ns * xx + nc * xz
        R[j, 0, 1], R[j, 1, 1], R[j, 2, 1] = nc * ux + ns * uz, uy, -ns * ux + nc * uz
        R[j, 0, 2], R[j, 1, 2], R[j, 2, 2] = nc * zx + ns * zz, zy, -ns * zx + nc * zz
    out[0, 0], out[0, 1], out[0, 2], out[0, 3] = 0.0, 0.0, 0.0, 1.0
    for j in range(1, parents.shape[0]):
        p = max(parents[j], 0)
        for r in range(3):
            for col in range(3):
                local[r, col] = R[p, 0, r] * R[j, 0, col] + R[p, 1, r] * R[j, 1, col] + R[p, 2, r] * R[j, 2, col]
        out[j, 0], out[j, 1], out[j, 2], out[j, 3] = matrix_quat(local)


@njit(cache=True, error_model="numpy")
def advance(y, control, track, body, rules):
    """Apply the output y (B, 353) in place; returns Hips translation, rotations and contacts."""
    yaw, hist_pos, hist_dir, hist_vel, hist_gait, hist_phase, fut_pos, fut_dir, fut_vel, fut_phase, pose = track
    parents, fps = body.parents, body.fps
    B, H, J = y.shape[0], hist_pos.shape[1], parents.shape[0]
    out_root = np.empty((B, 3), np.float32)
    out_rot = np.empty((B, J, 4), np.float32)
    contacts = np.empty((B, 2), np.bool_)
    R = np.empty((J, 3, 3))
    local = np.empty((3, 3))
    for b in range(B):
        # root motion
        yw = float(yaw[b])
        c, s = math.cos(yw), math.sin(yw)
        px, pz = hist_pos[b, H - 1, 0], hist_pos[b, H - 1, 1]
        still = min(max(1.0 - math.hypot(control[b, 0], control[b, 1]) / rules.stop_speed, 0.0), 1.0)
        keep = 1.0 - rules.root_hold * still
        dx, dz = turn_y(y[b, Y_DELTA] * keep, y[b, Y_DELTA + 1] * keep, c, s)
        nx, nz = np.float32(px + dx), np.float32(pz + dz)
        new_yaw = np.float32(wrap(yw + y[b, Y_DELTA + 2]))
        nc, ns = math.cos(new_yaw), math.sin(new_yaw)
        damp = 1.0 - still * (1.0 - rules.phase_damp)
        _shift_history(track, b)  # the new frame goes last
        # phases: advanced by the predicted frequency, blended with the predicted, at its amplitude
        for bone in range(NUM_BONES):
            cur_s, cur_c = hist_phase[b, H - 2, bone, 0], hist_phase[b, H - 2, bone, 1]
            pred_s, pred_c = y[b, Y_PHASE + 2 * bone], y[b, Y_PHASE + 2 * bone + 1]
            d = 2.0 * math.pi * y[b, Y_FREQ + bone] / fps
            # features are A (sin phi, cos phi): phi + d turns (s, c) into (s cos d + c sin d, c cos d - s sin d)
            adv_s = cur_s * math.cos(d) + cur_c * math.sin(d)
            adv_c = cur_c * math.cos(d) - cur_s * math.sin(d)
            bs = (1.0 - rules.phase_blend) * adv_s + rules.phase_blend * pred_s
            bc = (1.0 - rules.phase_blend) * adv_c + rules.phase_blend * pred_c
            scale = math.sqrt(pred_s * pred_s + pred_c * pred_c) / math.sqrt(max(bs * bs + bc * bc, 1e-16)) * damp
            hist_phase[b, H - 1, bone, 0], hist_phase[b, H - 1, bone, 1] = bs * scale, bc * scale
        hist_pos[b, H - 1, 0], hist_pos[b, H - 1, 1] = nx, nz
        hist_dir[b, H - 1, 0], hist_dir[b, H - 1, 1] = ns, nc
        hist_vel[b, H - 1, 0], hist_vel[b, H - 1, 1] = (nx - px) * fps, (nz - pz) * fps
        hist_gait[b, H - 1] = control[b, 3]
        # the predicted future, from the new character frame into the world
        for k in range(FUTURE):
            o = Y_TRAJ + k * TRAJ_OUT_CH
            fx, fz = turn_y(y[b, o], y[b, o + 1], nc, ns)
            fut_pos[b, k, 0], fut_pos[b, k, 1] = nx + fx, nz + fz
            fx, fz = turn_y(y[b, o + 2], y[b, o + 3], nc, ns)
            n = math.sqrt(max(fx * fx + fz * fz, 1e-16))
            fut_dir[b, k, 0], fut_dir[b, k, 1] = fx / n, fz / n
            fut_vel[b, k, 0], fut_vel[b, k, 1] = turn_y(y[b, o + 4], y[b, o + 5], nc, ns)
            for bone in range(NUM_BONES):
                for i in range(2):
                    fut_phase[b, k, bone, i] = y[b, Y_PHASE + 2 * NUM_BONES * (k + 1) + 2 * bone + i] * damp
        for j in range(pose.shape[1]):
            for ch in range(pose.shape[2]):
                pose[b, j, ch] = y[b, Y_POSE + j * pose.shape[2] + ch]
        yaw[b] = new_yaw
        _local_rotations(y[b], parents, nc, ns, R, local, out_rot[b])
        # Hips: the predicted offset from the ground root (character frame), into the world
        hx, hz = turn_y(y[b, Y_POSE], y[b, Y_POSE + 2], nc, ns)
        out_root[b, 0], out_root[b, 1], out_root[b, 2] = nx + hx, y[b, Y_POSE + 1], nz + hz
        contacts[b, 0] = y[b, Y_CONTACT] > rules.contact_threshold
        contacts[b, 1] = y[b, Y_CONTACT + 1] > rules.contact_threshold
    return out_root, out_rot, contacts
