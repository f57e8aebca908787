"""LPN-FiLM per-frame features: the layout of the network's input, gating input and output, and
their offline computation; the compiled kernels use the same formulas (`tests/reference/lpn_step.py`).

Conventions of `models.motion.features` (Y up, cm, yaw about +Y with 0 = +Z, horizontal (x, z)).
The character frame at t sits at the Hips on the ground, +Z along the facing. Trajectory samples
every 5th frame over +-30 frames (the paper's 13 at 30 fps).

Network input X (343):
    [0:91)     trajectory, 13 samples x (position xz, direction xz, velocity xz, gait), char. frame t
    [91:343)   pose of frame t, 21 body joints x (position, velocity, forward axis, up axis), char. frame t
Gating input G (104): local phase features of the 4 bones (phases.BONES), 13 samples x 4 x 2.
Network output Y (353), all about frame t+1:
    [0:36)     future trajectory, samples +5..+30 x (position xz, direction xz, velocity xz), char. frame t+1
    [36:288)   pose of frame t+1 in its own character frame (as in X)
    [288:291)  root delta: Hips ground displacement (x, z) in char. frame t, yaw change (radians)
    [291:347)  phase features at samples 0, +5, ..., +30 from t+1 (7 x 4 x 2)
    [347:351)  phase frequencies of the 4 bones at t+1 (Hz): the phase update
    [351:353)  foot contacts (left, right) at t+1
"""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import BODY, HIPS
from ..motion.features import facing_yaw, wrap_angle
from ..motion.rotations import quat_to_matrix, rotate_y
from ..motion.skeleton import Skeleton

FPS = 30.0
STEP = 5  # frames between trajectory samples
PAST = 6  # samples before the current frame
FUTURE = 6  # samples after it
SAMPLES = PAST + 1 + FUTURE  # 13
OFFSETS = np.arange(-PAST, FUTURE + 1) * STEP  # frame offsets of the samples
NB = len(BODY)  # 21
NUM_BONES = 4  # phase bones: Hand_L, Hand_R, Foot_L, Foot_R

TRAJ_CH = 7  # position xz, direction xz, velocity xz, gait
POSE_CH = 12  # position, velocity, forward axis, up axis
TRAJ_IN = slice(0, SAMPLES * TRAJ_CH)
POSE_IN = slice(TRAJ_IN.stop, TRAJ_IN.stop + NB * POSE_CH)
X_DIM = POSE_IN.stop  # 343
G_DIM = SAMPLES * NUM_BONES * 2  # 104

TRAJ_OUT_CH = 6
TRAJ_OUT = slice(0, FUTURE * TRAJ_OUT_CH)
POSE_OUT = slice(TRAJ_OUT.stop, TRAJ_OUT.stop + NB * POSE_CH)
DELTA_OUT = slice(POSE_OUT.stop, POSE_OUT.stop + 3)
PHASE_OUT = slice(DELTA_OUT.stop, DELTA_OUT.stop + (FUTURE + 1) * NUM_BONES * 2)
FREQ_OUT = slice(PHASE_OUT.stop, PHASE_OUT.stop + NUM_BONES)
CONTACT_OUT = slice(FREQ_OUT.stop, FREQ_OUT.stop + 2)
Y_DIM = CONTACT_OUT.stop  # 353

STYLE_DIM = NB * 6 + 3  # FiLM-generator clip features per frame: positions, velocities, root velocity xz, yaw rate


def direction(yaw: np.ndarray) -> np.ndarray:
    """(..., 2) facing direction (x, z) of a yaw."""
    return np.stack([np.sin(yaw), np.cos(yaw)], axis=-1)


def pose_features(
    positions: np.ndarray, velocities: np.ndarray, global_rot: np.ndarray, root: np.ndarray, yaw: np.ndarray
) -> np.ndarray:
    """(..., NB, 12) body-joint features; rotations as forward (+Z) and up (+Y) axes (continuous)."""
    y = -yaw[..., None]  # into the character frame
    mats = quat_to_matrix(global_rot[..., BODY, :])
    return np.concatenate(
        [
            rotate_y(positions[..., BODY, :] - root[..., None, :], y),
            rotate_y(velocities[..., BODY, :], y),
            rotate_y(mats[..., :, 2], y),
            rotate_y(mats[..., :, 1], y),
        ],
        axis=-1,
    )


def clip_frames(
    global_rot: np.ndarray, positions: np.ndarray, skeleton: Skeleton, fps: float = FPS
) -> dict[str, np.ndarray]:
    """A clip's ground root, yaw, joint and root velocities by backward differences, as a stream sees them."""
    yaw = facing_yaw(positions, skeleton)
    root = positions[:, HIPS] * np.array([1.0, 0.0, 1.0])
    vel = np.zeros_like(positions)
    vel[1:] = (positions[1:] - positions[:-1]) * fps
    return {"yaw": yaw, "root": root, "vel": vel, "root_vel": vel[:, HIPS][:, [0, 2]]}


def style_features(pose: np.ndarray, root_vel: np.ndarray, yaw: np.ndarray, fps: float = FPS) -> np.ndarray:
    """(F, STYLE_DIM) what a style *looks* like: positions, velocities, root velocity, yaw rate."""
    F = pose.shape[0]
    yaw_rate = np.zeros(F)
    yaw_rate[1:] = wrap_angle(np.diff(yaw)) * fps
    return np.concatenate([pose[:, :, :6].reshape(F, -1), rotate_y(root_vel, -yaw), yaw_rate[:, None]], axis=1)


def trajectory_input(
    pos: np.ndarray, dirs: np.ndarray, vel: np.ndarray, gait: np.ndarray, origin: np.ndarray, yaw: np.ndarray
) -> np.ndarray:
    """(..., 91) trajectory input from world samples (..., 13, 2), relative to `origin` and `yaw`."""
    y = -yaw[..., None]  # into the character frame
    p = rotate_y(pos - origin[..., None, :], y)
    d = rotate_y(dirs, y)
    v = rotate_y(vel, y)
    return np.concatenate([p, d, v, gait[..., None]], axis=-1).reshape(*pos.shape[:-2], SAMPLES * TRAJ_CH)
