"""The LPN-FiLM step in vectorised numpy, the reference the compiled kernels
(`models/lpn/kernels.py`) are held to: `tests/test_lpn.py` compares the two step by step. Same weights, same state, same outputs up
to float32 round-off; only `_control`, `_inputs`, `_network`, `_advance` and `_fk` differ (both
plant the feet with the shared compiled planter, `models.motion.feet`).
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.spatial.transform import Rotation

from models.interface import FrameBatch, State
from models.lpn import features as lf
from models.lpn.runtime import (
    CATCH_UP_S,
    CONTACT_THRESHOLD,
    CONTROL_BIAS,
    CONTROL_SMOOTH_S,
    CRAWL_SPEED,
    PHASE_BLEND,
    RUN_SPEED,
    STOP_PHASE_DAMP,
    STOP_ROOT_HOLD,
    STOP_SPEED,
    WALK_SPEED,
    LPNModel,
)
from models.motion.features import wrap_angle
from models.motion.rotations import rotate_y

PAST_IDX = np.arange(0, lf.PAST * lf.STEP + 1, lf.STEP)  # history rows of the 7 past-and-current samples


def to_world_xz(v: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Ground-plane vectors (..., 2) [x, z] from the character frame of facing `yaw` to the world."""
    c, s = np.cos(yaw), np.sin(yaw)
    x, z = v[..., 0], v[..., 1]
    return np.stack([c * x + s * z, -s * x + c * z], axis=-1)


def to_world(v: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    xz = to_world_xz(v[..., [0, 2]], yaw)
    return np.stack([xz[..., 0], v[..., 1], xz[..., 1]], axis=-1)


def rotations_from_axes(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) whose +Z column is `forward` and +Y column is `up`
    (orthonormalised: forward is kept, up made perpendicular)."""
    z = forward / np.sqrt(np.maximum((forward * forward).sum(-1, keepdims=True), 1e-18))
    y = up - (up * z).sum(-1, keepdims=True) * z
    y = y / np.sqrt(np.maximum((y * y).sum(-1, keepdims=True), 1e-18))
    x = y[..., [1, 2, 0]] * z[..., [2, 0, 1]] - y[..., [2, 0, 1]] * z[..., [1, 2, 0]]  # y x z
    return np.stack([x, y, z], axis=-1)


def _elu(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def _layer_norm(x: np.ndarray) -> np.ndarray:
    m = x.mean(-1, keepdims=True)
    v = ((x - m) ** 2).mean(-1, keepdims=True)
    return (x - m) / np.sqrt(v + 1e-5)


def _normalise(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(np.maximum((v * v).sum(-1, keepdims=True), 1e-16))


class NumpyLPNModel(LPNModel):
    """LPNModel with the numpy step (one vectorised numpy expression per formula, over the batch)."""

    def _control(
        self, s: State, frames: FrameBatch, root: np.ndarray, rot_in: np.ndarray, fresh: np.ndarray
    ) -> np.ndarray:
        """(B, 4) control (forward, side in cm/s, yaw, gait): given rows as they are, the others derived
        from the input frames."""
        B = root.shape[0]
        given = np.zeros(B, bool) if frames.control is None else np.asarray(frames.control)[:, 4] > 0.5
        out = np.zeros((B, 4), np.float32)
        if given.any():
            c = np.asarray(frames.control, np.float32)[given]
            out[given] = np.stack([c[:, 0] * 100.0, c[:, 1] * 100.0, c[:, 2], c[:, 3]], axis=1)
        derive = np.flatnonzero(~given)
        # the input tracker advances every frame so a session can switch between modes smoothly
        xz = root[:, [0, 2]]
        step = np.where((s["frame"] > 0)[:, None], xz - s["in_pos"], 0.0)
        a = 1.0 - np.exp(-1.0 / (self.fps * CONTROL_SMOOTH_S))
        s["in_vel"] = (s["in_vel"] + a * (step * self.fps - s["in_vel"])).astype(np.float32)
        s["in_pos"] = xz.astype(np.float32)
        s["lead"] = np.where(given, 0.0, s["lead"]).astype(np.float32)
        if len(derive):
            _, gpos = self._fk(root[derive], rot_in[derive])
            yaw = self._facing(gpos)
            vel = s["in_vel"][derive].astype(np.float64)
            speed = np.linalg.norm(rotate_y(vel, -yaw), axis=-1)
            # where the input is slower than the training walks (CRAWL_SPEED .. WALK_SPEED), slowed by
            # how much farther the character walked than the input (its lead, made up CATCH_UP_S on)
            slow = np.clip((WALK_SPEED - np.linalg.norm(vel, axis=-1)) / (WALK_SPEED - CRAWL_SPEED), 0.0, 1.0)
            walked = np.linalg.norm(s["hist_pos"][derive, -1] - s["hist_pos"][derive, -2], axis=-1)
            lead = s["lead"][derive] + slow * (walked - np.linalg.norm(step[derive], axis=-1))
            lead = np.where(lead > 0.0, lead, lead * np.exp(-1.0 / (self.fps * CATCH_UP_S)))  # shortfalls fade
            s["lead"][derive] = lead
            share = 1.0 - slow * np.clip(lead / (CATCH_UP_S * np.maximum(np.linalg.norm(vel, axis=-1), 1e-9)), 0.0, 1.0)
            local = rotate_y(share[:, None] * vel, -yaw)
            out[derive] = np.stack([local[:, 1], local[:, 0], yaw, (speed > RUN_SPEED).astype(np.float32)], axis=1)
        return out

    def _inputs(self, s: State, control: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Blend the future trajectory toward the control, then build X and G."""
        B = control.shape[0]
        yaw, pos = s["yaw"], s["hist_pos"][:, -1]
        want_yaw = control[:, 2]
        want_vel = to_world_xz(np.stack([control[:, 1], control[:, 0]], -1), want_yaw)
        k = np.arange(1, lf.FUTURE + 1, dtype=np.float32)
        tau = (k * lf.STEP / self.fps)[None, :, None]
        beta = (1.0 - (1.0 - k / lf.FUTURE) ** CONTROL_BIAS)[None, :, None]
        turn = wrap_angle(want_yaw - yaw)[:, None] * (k / lf.FUTURE)[None]
        target_pos = pos[:, None] + want_vel[:, None] * tau
        target_dir = lf.direction(yaw[:, None] + turn)
        s["fut_pos"] = (s["fut_pos"] + beta * (target_pos - s["fut_pos"])).astype(np.float32)
        s["fut_dir"] = _normalise(s["fut_dir"] + beta * (target_dir - s["fut_dir"])).astype(np.float32)
        s["fut_vel"] = (s["fut_vel"] + beta * (want_vel[:, None] - s["fut_vel"])).astype(np.float32)
        gait = np.concatenate([s["hist_gait"][:, PAST_IDX], np.repeat(control[:, 3:4], lf.FUTURE, 1)], 1)
        traj = lf.trajectory_input(
            np.concatenate([s["hist_pos"][:, PAST_IDX], s["fut_pos"]], 1),
            np.concatenate([s["hist_dir"][:, PAST_IDX], s["fut_dir"]], 1),
            np.concatenate([s["hist_vel"][:, PAST_IDX], s["fut_vel"]], 1),
            gait,
            pos,
            yaw,
        )
        x = np.concatenate([traj, s["pose"].reshape(B, -1)], 1)
        g = np.concatenate([s["hist_phase"][:, PAST_IDX], s["fut_phase"]], 1).reshape(B, -1)
        return x.astype(np.float32), g.astype(np.float32)

    def _network(self, x: np.ndarray, g: np.ndarray, film: np.ndarray) -> np.ndarray:
        """Denormalised output (B, Y_DIM); the same maths as `network.LPN.forward` in eval mode."""
        h = g / self.g_scale
        for i, (W, b) in enumerate(self.gating):
            h = h @ W + b
            if i < 2:
                h = _elu(h)
        alpha = np.exp(h - h.max(-1, keepdims=True))
        alpha /= alpha.sum(-1, keepdims=True)
        h = (x - self.x_mean) / self.x_std
        for i, (W, b, n_out) in enumerate(self.layers):
            h = np.matmul(alpha[:, None, :], (h @ W).reshape(-1, self.E, n_out))[:, 0] + alpha @ b
            if i < 2:
                h = _elu(_layer_norm(h) * (1.0 + film[:, 2 * i]) + film[:, 2 * i + 1])
        return h * self.y_std + self.y_mean

    def _advance(self, s: State, y: np.ndarray, control: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply the prediction: move the root, shift the history, store pose/phases/future; returns
        the output Hips translation, local rotations, contacts and world rotation matrices.

        Stopping: the training clips hardly ever stand still after moving, so on its own the network
        keeps stepping when asked to stop. While the wanted speed is below STOP_SPEED the phases
        (current and future) are damped toward zero each frame, the amplitude the network learned
        for standing at the start of a take, so its experts for standing take over, and most of the
        predicted root translation is held back (alone, each leaves a 30-60 cm/s shuffle)."""
        B = y.shape[0]
        yaw, pos = s["yaw"], s["hist_pos"][:, -1]
        delta = y[:, lf.DELTA_OUT]
        still = np.clip(1.0 - np.hypot(control[:, 0], control[:, 1]) / STOP_SPEED, 0.0, 1.0)
        new_pos = pos + to_world_xz(delta[:, :2] * (1.0 - STOP_ROOT_HOLD * still)[:, None], yaw)
        new_yaw = wrap_angle(yaw + delta[:, 2]).astype(np.float32)
        vel = (new_pos - pos) * self.fps
        # phases: the current phase advanced by the predicted frequency, blended with the predicted one
        ph = y[:, lf.PHASE_OUT].reshape(B, lf.FUTURE + 1, lf.NUM_BONES, 2)
        cur = s["hist_phase"][:, -1]
        angle = 2 * np.pi * y[:, lf.FREQ_OUT] / self.fps
        c, sn = np.cos(angle), np.sin(angle)
        # features are A (sin phi, cos phi): advancing phi by d rotates (s, c) -> (s cos d + c sin d, c cos d - s sin d)
        advanced = np.stack([cur[..., 0] * c + cur[..., 1] * sn, cur[..., 1] * c - cur[..., 0] * sn], -1)
        blend = _normalise((1 - PHASE_BLEND) * advanced + PHASE_BLEND * ph[:, 0])
        next_phase = blend * np.linalg.norm(ph[:, 0], axis=-1, keepdims=True)
        damp = (1.0 - still * (1.0 - STOP_PHASE_DAMP))[:, None, None]
        next_phase = next_phase * damp

        def push(key: str, value: np.ndarray) -> None:
            s[key] = np.concatenate([s[key][:, 1:], value[:, None].astype(np.float32)], 1)

        push("hist_pos", new_pos)
        push("hist_dir", lf.direction(new_yaw))
        push("hist_vel", vel)
        push("hist_gait", control[:, 3])
        push("hist_phase", next_phase)
        traj = y[:, lf.TRAJ_OUT].reshape(B, lf.FUTURE, lf.TRAJ_OUT_CH)
        ny = new_yaw[:, None]
        s["fut_pos"] = (new_pos[:, None] + to_world_xz(traj[..., 0:2], ny)).astype(np.float32)
        s["fut_dir"] = _normalise(to_world_xz(traj[..., 2:4], ny)).astype(np.float32)
        s["fut_vel"] = to_world_xz(traj[..., 4:6], ny).astype(np.float32)
        s["fut_phase"] = (ph[:, 1:] * damp[:, None]).astype(np.float32)
        pose = y[:, lf.POSE_OUT].reshape(B, lf.NB, lf.POSE_CH)
        s["pose"] = pose.astype(np.float32)
        s["yaw"] = new_yaw
        # output frame: world rotations from the forward/up axes, then local rotations
        g_char = rotations_from_axes(pose[..., 6:9], pose[..., 9:12])  # (B, NB, 3, 3) character frame
        R_yaw = np.zeros((B, 3, 3), np.float32)
        cy, sy = np.cos(new_yaw), np.sin(new_yaw)
        R_yaw[:, 0, 0], R_yaw[:, 0, 2], R_yaw[:, 1, 1], R_yaw[:, 2, 0], R_yaw[:, 2, 2] = cy, sy, 1.0, -sy, cy
        g_world = np.concatenate(
            [np.broadcast_to(np.eye(3, dtype=np.float32), (B, 1, 3, 3)), R_yaw[:, None] @ g_char], 1
        )  # (B, 22, 3, 3), joint_Root identity
        parents = np.maximum(self.parents, 0)
        local = np.swapaxes(g_world[:, parents], -1, -2) @ g_world
        local[:, 0] = np.eye(3)
        hips = pose[:, 0, :3]
        out_root = np.stack([new_pos[:, 0], hips[:, 1], new_pos[:, 1]], -1) + to_world(
            np.stack([hips[:, 0], 0 * hips[:, 1], hips[:, 2]], -1), new_yaw
        )
        contacts = y[:, lf.CONTACT_OUT] > CONTACT_THRESHOLD
        quats = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_quat().reshape(B, -1, 4)  # C code: 10x numpy's
        return out_root.astype(np.float32), quats.astype(np.float32), contacts

    def _fk(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (B, 22, 4) and positions (B, 22, 3); joint_Root static at the origin."""
        from models.motion.skeleton import fk

        trans = np.broadcast_to(self.offsets, rotations.shape[:-1] + (3,)).copy()
        trans[:, lf.HIPS] = root
        g_rot, g_pos = fk(rotations, trans, self.parents)
        return g_rot.astype(np.float32), g_pos.astype(np.float32)


def numpy_twin(model: LPNModel) -> NumpyLPNModel:
    """The numpy step on `model`'s own arrays (weights, styles): no second copy of the 8 MB of
    weights, so a benchmark alternating the two steps does not evict one's weights for the other's."""
    twin = copy.copy(model)
    twin.__class__ = NumpyLPNModel
    return twin


def in_float32(model: LPNModel) -> LPNModel:
    """`model` (weights and styles shared) with float32 expert products, as the numpy step
    computes them (bfloat16 products: tests/test_rowwise.py)."""
    twin = copy.copy(model)
    twin.bfloat16 = False
    twin.__dict__.pop("_products", None)
    return twin
