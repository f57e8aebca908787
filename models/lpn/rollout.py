"""Closed-loop training: K-frame rollouts in which the network reads back its own output, as the
runtime makes it do: teacher forcing alone never shows a controller its own mistakes.

A rollout starts on a recorded frame; then pose, root track, trajectory (the predicted future
blended toward the recording, by the runtime's rule) and phases come from the network's previous
prediction, each step scored against the recorded next frame. "World" is the first character frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch

from . import features as lf
from .runtime import CONTROL_BIAS, PHASE_BLEND

if TYPE_CHECKING:
    from .network import LPN

SAMPLE = lf.TRAJ_CH  # pos xz, dir xz, vel xz, gait
PHASE = lf.NUM_BONES * 2


def to_world(v: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """(..., 2) vectors in the frame facing `yaw` into the world."""
    c, s = torch.cos(yaw)[..., None], torch.sin(yaw)[..., None]
    x, z = v[..., 0:1], v[..., 1:2]
    return torch.cat([c * x + s * z, -s * x + c * z], dim=-1)


def to_local(v: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(yaw)[..., None], torch.sin(yaw)[..., None]
    x, z = v[..., 0:1], v[..., 1:2]
    return torch.cat([c * x - s * z, s * x + c * z], dim=-1)


def rollout_starts(clip: np.ndarray, style: np.ndarray, frames: int) -> dict[int, np.ndarray]:
    """Per style, sample indices beginning `frames` consecutive samples of one clip."""
    n = len(clip) - frames + 1
    ok = np.zeros(len(clip), bool)
    ok[:n] = clip[:n] == clip[frames - 1 :]
    return {int(k): np.flatnonzero(ok & (style == k)) for k in np.unique(style)}


def control_weights(device: torch.device) -> torch.Tensor:
    """(6, 1) share of the recording in each future sample (the runtime's control blend)."""
    k = torch.arange(1, lf.FUTURE + 1, dtype=torch.float32, device=device) / lf.FUTURE
    return (1.0 - (1.0 - k) ** CONTROL_BIAS)[:, None]


def _samples(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Trajectory input (B, 91) -> positions, directions, velocities (B, 13, 2) and gait (B, 13)."""
    t = x[:, lf.TRAJ_IN].view(-1, lf.SAMPLES, SAMPLE)
    return t[..., 0:2], t[..., 2:4], t[..., 4:6], t[..., 6]


def rollout(
    net: LPN,
    X: torch.Tensor,
    G: torch.Tensor,
    Y: torch.Tensor,
    film: torch.Tensor,
    closed: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """K steps on B recorded windows; `closed` (B,): rollouts fed their own output. (predictions, targets)."""
    B, K = X.shape[:2]
    dev = X.device
    beta = control_weights(dev)
    cl = closed.view(B, 1).float()
    # the recording's root track in world (the first frame's character frame), from its root deltas
    d = Y[..., lf.DELTA_OUT]
    o_rec, yaw_rec = [torch.zeros(B, 2, device=dev)], [torch.zeros(B, device=dev)]
    for k in range(K - 1):
        o_rec.append(o_rec[k] + to_world(d[:, k, :2], yaw_rec[k]))
        yaw_rec.append(yaw_rec[k] + d[:, k, 2])
    o_net, yaw_net = [o_rec[0]], [yaw_rec[0]]  # the network's own track, frame by frame
    phase_net = [G[:, 0].view(B, lf.SAMPLES, PHASE)[:, lf.PAST]]  # its current phase, frame by frame
    tracks = Tracks(o_rec, yaw_rec, o_net, yaw_net, phase_net)
    preds, prev = [], None
    for k in range(K):
        x_rec, g_rec = X[:, k], G[:, k]
        if prev is None:
            x, g = x_rec, g_rec
        else:
            x_own, g_own, o, yw, ph = _own_inputs(prev, x_rec, g_rec, k, tracks, beta)
            o_net.append(torch.where(cl > 0, o, o_rec[k]))
            yaw_net.append(torch.where(closed, yw, yaw_rec[k]))
            phase_net.append(torch.where(cl > 0, ph, g_rec.view(B, lf.SAMPLES, PHASE)[:, lf.PAST]))
            x = torch.where(cl > 0, x_own, x_rec)
            g = torch.where(cl > 0, g_own, g_rec)
        pred = net(net.normalise_x(x), net.normalise_g(g), film)
        preds.append(pred)
        prev = net.denormalise_y(pred.float())
    return torch.stack(preds, 1), net.normalise_y(Y)


class Tracks(NamedTuple):
    """A rollout's root tracks in world per frame: the recording's and the network's (with its phase)."""

    rec_pos: list[torch.Tensor]  # (B, 2) each
    rec_yaw: list[torch.Tensor]  # (B,)
    pos: list[torch.Tensor]
    yaw: list[torch.Tensor]
    phase: list[torch.Tensor]  # (B, PHASE)


def _own_inputs(
    y: torch.Tensor, x_rec: torch.Tensor, g_rec: torch.Tensor, k: int, tracks: Tracks, beta: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Step k's input from the previous output y and the network's new root, yaw and phase."""
    o_rec, yaw_rec, o_net, yaw_net, phase_net = tracks
    fps = lf.FPS
    B = y.shape[0]
    delta = y[:, lf.DELTA_OUT]
    o = o_net[k - 1] + to_world(delta[:, :2], yaw_net[k - 1])
    yw = yaw_net[k - 1] + delta[:, 2]
    # the recording's samples in world; as the control, moved along with the network's root
    pos, dirs, vel, gait = _samples(x_rec)
    rec_pos = o_rec[k][:, None] + to_world(pos, yaw_rec[k][:, None])
    ctrl_pos = rec_pos + (o - o_rec[k])[:, None]
    rec_dir, rec_vel = to_world(dirs, yaw_rec[k][:, None]), to_world(vel, yaw_rec[k][:, None])
    # past and current samples: the network's own frames where the rollout made them
    P_pos, P_dir, P_vel = [], [], []
    track_o, track_yaw = [*o_net, o], [*yaw_net, yw]
    for i in range(lf.PAST + 1):
        m = k + (i - lf.PAST) * lf.STEP
        if m >= 1:
            P_pos.append(track_o[m])
            P_dir.append(torch.stack([torch.sin(track_yaw[m]), torch.cos(track_yaw[m])], -1))
            P_vel.append((track_o[m] - track_o[m - 1]) * fps)
        else:
            P_pos.append(rec_pos[:, i])  # before the rollout: the recorded path
            P_dir.append(rec_dir[:, i])
            P_vel.append(rec_vel[:, i])
    # future samples: the predicted future blended toward the recording (the control)
    fut = y[:, lf.TRAJ_OUT].view(B, lf.FUTURE, lf.TRAJ_OUT_CH)
    f_pos = o[:, None] + to_world(fut[..., 0:2], yw[:, None])
    f_dir = to_world(fut[..., 2:4], yw[:, None])
    f_vel = to_world(fut[..., 4:6], yw[:, None])
    s = slice(lf.PAST + 1, lf.SAMPLES)
    f_pos = f_pos + beta * (ctrl_pos[:, s] - f_pos)
    f_dir = f_dir + beta * (rec_dir[:, s] - f_dir)
    f_dir = f_dir / f_dir.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    f_vel = f_vel + beta * (rec_vel[:, s] - f_vel)
    w_pos = torch.cat([torch.stack(P_pos, 1), f_pos], 1)
    w_dir = torch.cat([torch.stack(P_dir, 1), f_dir], 1)
    w_vel = torch.cat([torch.stack(P_vel, 1), f_vel], 1)
    yv = yw[:, None]
    traj = torch.cat(
        [to_local(w_pos - o[:, None], yv), to_local(w_dir, yv), to_local(w_vel, yv), gait[..., None]], -1
    ).reshape(B, -1)
    x = torch.cat([traj, y[:, lf.POSE_OUT]], -1)
    # phases: current = previous advanced by the predicted frequency, blended with the predicted
    pred_ph = y[:, lf.PHASE_OUT].view(B, lf.FUTURE + 1, PHASE)
    cur = phase_net[k - 1].view(B, lf.NUM_BONES, 2)
    step = 2 * np.pi * y[:, lf.FREQ_OUT] / fps
    c, sn = torch.cos(step), torch.sin(step)
    adv = torch.stack([cur[..., 0] * c + cur[..., 1] * sn, cur[..., 1] * c - cur[..., 0] * sn], -1)
    p0 = pred_ph[:, 0].view(B, lf.NUM_BONES, 2)
    blend = (1 - PHASE_BLEND) * adv + PHASE_BLEND * p0
    scale = p0.norm(dim=-1, keepdim=True) / blend.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    ph = (blend * scale).reshape(B, PHASE)
    rec_g = g_rec.view(B, lf.SAMPLES, PHASE)
    track_ph = [*phase_net, ph]
    past = [
        track_ph[k + (i - lf.PAST) * lf.STEP] if k + (i - lf.PAST) * lf.STEP >= 1 else rec_g[:, i]
        for i in range(lf.PAST)
    ]
    g = torch.cat([torch.stack(past, 1), ph[:, None], pred_ph[:, 1:]], 1).reshape(B, -1)
    return x, g, o, yw, ph
