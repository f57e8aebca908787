"""`models.motion.hands` measured in numpy over whole clips: the reference the compiled hand
meter (`models.motion.hands_kernels.hand_step`) and the stream's raised-arm stages are tested against."""

from __future__ import annotations

import numpy as np

from models.motion.hands import SWAY_FRAMES, _arm_chain, _over_clip, hand_offsets, raise_share
from models.motion.rotations import quat_apply, quat_mul
from models.motion.skeleton import Motion, Skeleton


def hand_offsets_of(rotations: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """(B, 2, 3) `hand_offsets` from local rotations (B, J, 4) alone (numpy forward kinematics
    over the arm chains; the reference of `hand_step`)."""
    chain, hands, shoulders = _arm_chain(skeleton)
    q = np.asarray(rotations, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    g_rot: dict[int, np.ndarray] = {}
    g_pos: dict[int, np.ndarray] = {}
    for j in chain:
        p = int(skeleton.parents[j])
        if p < 0:
            g_rot[j], g_pos[j] = q[:, j], np.zeros((len(q), 3))
        else:
            g_rot[j] = quat_mul(g_rot[p], q[:, j])
            g_pos[j] = g_pos[p] + quat_apply(g_rot[p], np.broadcast_to(skeleton.offsets[j], (len(q), 3)))
    return np.stack([g_pos[h] - g_pos[s] for h, s in zip(hands, shoulders)], axis=1)


def rise(
    before: np.ndarray, offsets: np.ndarray, prev_offsets: np.ndarray, has_prev: np.ndarray, fps: float
) -> np.ndarray:
    """(B, 2) each hand's averaged vertical speed (cm/s, up or down) against its shoulder after
    this frame, as `hands.sway` averages the horizontal one (the reference of `hand_step`'s rise)."""
    speed = np.abs(np.asarray(offsets)[..., 1] - np.asarray(prev_offsets)[..., 1]) * fps
    return np.where(has_prev[:, None], before + (speed - before) / SWAY_FRAMES, 0.0)


def clip_rise(offsets: np.ndarray, fps: float) -> np.ndarray:
    """(T, 2) `rise` over every frame of a clip's `hand_offsets` (T, 2, 3), as a stream sees it."""
    return _over_clip(rise, offsets, fps)


def raised_frames(motion: Motion, side: int | None = None) -> np.ndarray:
    """(T,) bool: the frames of a Bandai Namco `Motion` with a hand (`side` 0: the left, 1: the
    right; None: either) at its shoulder or above (more than half way up `RAISE_RAMP_CM`)."""
    heights = hand_offsets(motion.global_positions())[..., 1]
    return raise_share(heights.max(-1) if side is None else heights[:, side]) > 0.5
