"""Running or not, frame by frame from the input alone: which of Style-ERD's rotation priors a
frame gets (`rotation_prior.py`).

Priors over every content carried runs toward walks, so runs get priors fitted on runs alone. A
frame's share ramps with the input's Hips speed over `RUN_RAMP_CM_S` (neutral walks' p99 to runs'
p5), averaged over about a running step (`SPEED_SMOOTHING`), eased in over a session's start.
"""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import HIPS

RUN_RAMP_CM_S = (170.0, 210.0)
START_FRAMES = 5  # a session eases into the run priors over its first frames (`eased_in`)
SPEED_SMOOTHING = 2.0 / 11.0  # the exponential average's weight on the newest frame (~10-frame window)
UNMEASURED = -1.0  # a session's average before its second frame


def hips_speed(pos: np.ndarray, prev_pos: np.ndarray, has_prev: np.ndarray, fps: float) -> np.ndarray:
    """(B,) horizontal Hips speed (cm/s) from the previous frame's positions; 0 without one."""
    step = pos[:, HIPS, ::2] - prev_pos[:, HIPS, ::2]  # x and z
    return np.where(has_prev, np.hypot(step[:, 0], step[:, 1]) * fps, 0.0)


def clip_hips_speed(pos: np.ndarray, fps: float) -> np.ndarray:
    """(T,) `hips_speed` of every frame of a clip's world positions (T, J, 3), as a stream sees it."""
    prev = np.concatenate([pos[:1], pos[:-1]])
    return hips_speed(pos, prev, np.arange(len(pos)) > 0, fps)


def smoothed_speed(average: np.ndarray, speed: np.ndarray, has_prev: np.ndarray) -> np.ndarray:
    """(B,) the Hips speed's running average: `UNMEASURED`, then the first speed, then averaged."""
    average, speed = np.asarray(average, np.float64), np.asarray(speed, np.float64)
    moved = np.where(average < 0.0, speed, average + SPEED_SMOOTHING * (speed - average))
    return np.where(has_prev, moved, UNMEASURED)


def clip_smoothed_speed(pos: np.ndarray, fps: float) -> np.ndarray:
    """(T,) `smoothed_speed` of every frame of a clip's world positions (T, J, 3), as a stream sees it."""
    raw = clip_hips_speed(pos, fps)
    out = np.empty(len(raw))
    average = np.array([UNMEASURED])
    for t, v in enumerate(raw):
        average = smoothed_speed(average, np.array([v]), np.array([t > 0]))
        out[t] = average[0]
    return out


def run_share(speed: np.ndarray) -> np.ndarray:
    """(B,) how far each frame is a run: linear over the ramp (unmeasured: 0)."""
    lo, hi = RUN_RAMP_CM_S
    return np.clip((np.asarray(speed, np.float64) - lo) / (hi - lo), 0.0, 1.0)


def eased_in(share: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(B,) the run share faded in over `START_FRAMES`, so a stream starting mid-run does not jerk."""
    return np.asarray(share, np.float64) * np.minimum(np.asarray(frame, np.float64) / START_FRAMES, 1.0)
