"""Per-frame judge features (causal): root-relative joint positions and velocities in the facing
frame, root velocity and yaw rate; BN's `joint_Root` left out (it says where the actor stands)."""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import body_joints
from ..motion.features import compute_features
from ..motion.skeleton import Motion

NUM_BODY_JOINTS = 21  # Bandai Namco: 22 joints minus joint_Root
FEATURE_DIM = NUM_BODY_JOINTS * 6 + 4


def _body(motion: Motion) -> slice:
    """The body's joints (`bn_skeleton.body_joints`): a static root, if any, comes first."""
    return slice(len(motion.skeleton.names) - len(body_joints(motion.skeleton.names)), None)


def clip_features(motion: Motion) -> np.ndarray:
    """(F, FEATURE_DIM) float32."""
    f = compute_features(motion)
    body = _body(motion)
    return np.concatenate(
        [
            f.local_positions[:, body].reshape(len(f.yaw), -1),
            f.joint_velocities[:, body].reshape(len(f.yaw), -1),
            f.root_velocity,
            f.yaw_rate[:, None],
        ],
        axis=1,
    ).astype(np.float32)


def pad_to(x: np.ndarray, length: int) -> np.ndarray:
    """Hold the last frame so the clip has at least `length` frames."""
    if len(x) >= length:
        return x
    return np.concatenate([x, np.repeat(x[-1:], length - len(x), 0)])


def windows(x: np.ndarray, length: int, stride: int) -> np.ndarray:
    """(N, length, D) sliding windows (padded when short), the last aligned to the clip's end."""
    x = pad_to(x, length)
    starts = list(range(0, len(x) - length + 1, stride))
    if starts[-1] != len(x) - length:
        starts.append(len(x) - length)
    return np.stack([x[s : s + length] for s in starts])
