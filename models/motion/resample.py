"""Time resampling of motions: slerp for rotations, linear interpolation for translations.

Output frame k sits at time k / fps; frames run up to the source's last frame time, so the
duration (last frame time) is kept to within one output frame. When the target rate divides the
source rate (120 -> 30 fps) output frames coincide with source frames and copy them exactly.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .rotations import quat_canonical
from .skeleton import Motion


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Vectorised shortest-path slerp between unit quaternions (..., 4); t broadcasts as (..., 1)."""
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)  # stored data may be float32-rounded
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    t = np.asarray(t, float)
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    near = sin < 1e-6
    safe = np.where(near, 1.0, sin)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def resampled_length(num_frames: int, src_fps: float, fps: float) -> int:
    """How many frames `num_frames` at `src_fps` become at `fps` (known before any is made)."""
    if num_frames <= 1:
        return num_frames
    return int(np.floor((num_frames - 1) * fps / src_fps + 1e-6)) + 1


def resample_times(num_frames: int, src_fps: float, fps: float) -> np.ndarray:
    """Source-frame coordinates (fractional indices) of the output frames."""
    if num_frames <= 1:
        return np.zeros(num_frames)
    n_out = resampled_length(num_frames, src_fps, fps)
    return np.minimum(np.arange(n_out) * (src_fps / fps), num_frames - 1)


def resample(motion: Motion, fps: float) -> Motion:
    """The motion at `fps` frames per second (a new Motion; the input is not modified)."""
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if abs(fps - motion.fps) < 1e-9 or motion.num_frames <= 1:
        return replace(
            motion, rotations=motion.rotations.copy(), translations=motion.translations.copy(), fps=float(fps)
        )
    x = resample_times(motion.num_frames, motion.fps, fps)
    i0 = np.floor(x + 1e-9).astype(int).clip(0, motion.num_frames - 1)
    i1 = np.minimum(i0 + 1, motion.num_frames - 1)
    frac = (x - i0).clip(0.0, 1.0)
    frac[frac < 1e-9] = 0.0
    w = frac[:, None, None]
    rot = slerp(motion.rotations[i0], motion.rotations[i1], w)
    exact = frac == 0.0
    rot[exact] = motion.rotations[i0[exact]]  # coinciding frames are copied (up to quaternion sign)
    trans = (1.0 - w) * motion.translations[i0] + w * motion.translations[i1]
    return replace(motion, rotations=quat_canonical(rot), translations=trans, fps=float(fps))
