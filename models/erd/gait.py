"""Running or not, frame by frame from the input alone: which of Style-ERD's rotation priors a
frame gets (`rotation_prior.py`).

Priors fitted over every content carried runs toward walks and gestures, so runs get priors
fitted on runs alone (`*_prior_run.npz`). A frame's share of them ramps with the input's
horizontal Hips speed over `RUN_RAMP_CM_S` (from the TRAIN neutral walks' p99 to the runs' p5).
Causal: the speed is the step from the previous input frame, averaged over about a running step
(`SPEED_SMOOTHING`; frame by frame a run's speed swing flipped the arms between priors); a
session's first frame counts as standing, and it eases into the run priors (`eased_in`).
"""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import HIPS

RUN_RAMP_CM_S = (170.0, 210.0)
START_FRAMES = 5  # a session eases into the run priors over its first frames (`eased_in`; 10 cost a validation row)
SPEED_SMOOTHING = 2.0 / 11.0  # the exponential average's weight on the newest frame (~10-frame window)
UNMEASURED = -1.0  # a session's average before its second frame


def hips_speed(pos: np.ndarray, prev_pos: np.ndarray, has_prev: np.ndarray, fps: float) -> np.ndarray:
    """(B,) horizontal Hips speed (cm/s) from the previous input frame's world joint positions
    (B, J, 3) to this one's; 0 where there is no previous frame."""
    step = pos[:, HIPS, ::2] - prev_pos[:, HIPS, ::2]  # x and z
    return np.where(has_prev, np.hypot(step[:, 0], step[:, 1]) * fps, 0.0)


def clip_hips_speed(pos: np.ndarray, fps: float) -> np.ndarray:
    """(T,) `hips_speed` of every frame of a clip's world positions (T, J, 3), as a stream sees it."""
    prev = np.concatenate([pos[:1], pos[:-1]])
    return hips_speed(pos, prev, np.arange(len(pos)) > 0, fps)


def smoothed_speed(average: np.ndarray, speed: np.ndarray, has_prev: np.ndarray) -> np.ndarray:
    """(B,) the running average of the Hips speed after this frame: `UNMEASURED` until a frame
    has a previous one, then the first measured speed, then exponentially averaged."""
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
    """(B,) how far each frame is a run: 0 up to the ramp, 1 past it, linear between (an
    unmeasured speed, `UNMEASURED` < 0: 0)."""
    lo, hi = RUN_RAMP_CM_S
    return np.clip((np.asarray(speed, np.float64) - lo) / (hi - lo), 0.0, 1.0)


def eased_in(share: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(B,) the run share at each row's `frame` (frames the session saw before this one), faded in
    over its first `START_FRAMES`: a stream that starts mid-run counts its first frame as standing,
    and taking the run priors whole on its second frame turned the head in one frame."""
    return np.asarray(share, np.float64) * np.minimum(np.asarray(frame, np.float64) / START_FRAMES, 1.0)
