"""Standing, walking or running, frame by frame from the input alone: which of Style-ERD's
rotation priors a frame gets (`rotation_prior.py`).

Priors over every content carried runs toward walks and standing poses toward a walk's, so runs and
standing clips get priors fitted on them alone. A frame's gait share ramps with the input's Hips
speed: from -1 (standing) to 0 over `STAND_RAMP_CM_S` (neutral standing clips' p99.9 doubled to
`gait_split.MOVING_CM_S`), then to 1 (running) over `RUN_RAMP_CM_S` (neutral walks' p99 to runs'
p5); the speed averaged over about a running step (`SPEED_SMOOTHING`). The share follows that
target at most `GAIT_RATE` a frame from 0 at a session's start: the priors differ by up to ~15
degrees on a joint, and a stop or a start crosses the stand ramp in a few frames.
"""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import HIPS
from ..motion.gait_split import MOVING_CM_S

RUN_RAMP_CM_S = (170.0, 210.0)
STAND_RAMP_CM_S = (10.0, MOVING_CM_S)
GAIT_RATE = 1.0 / 15.0  # the most a frame's gait share moves from the last frame's (`followed`)
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


def stand_share(speed: np.ndarray) -> np.ndarray:
    """(B,) how far each frame stands: 1 under the ramp, linear over it (unmeasured: 0)."""
    lo, hi = STAND_RAMP_CM_S
    speed = np.asarray(speed, np.float64)
    return np.where(speed == UNMEASURED, 0.0, np.clip((hi - speed) / (hi - lo), 0.0, 1.0))


def gait_share(speed: np.ndarray) -> np.ndarray:
    """(B,) -1 standing, 0 walking, 1 running, linear over each ramp (`StageFrame.gait`)."""
    return run_share(speed) - stand_share(speed)


def followed(last: np.ndarray, target: np.ndarray, has_prev: np.ndarray) -> np.ndarray:
    """(B,) this frame's gait share: `target` approached from the `last` by at most `GAIT_RATE`
    (0 on a session's first frame), so neither a stream starting mid-run nor a stop jerks."""
    step = np.clip(np.asarray(target, np.float64) - last, -GAIT_RATE, GAIT_RATE)
    return np.where(has_prev, last + step, 0.0)


def clip_gait(pos: np.ndarray, fps: float) -> np.ndarray:
    """(T,) the gait share of every frame of a clip's world positions (T, J, 3), as a stream sees it."""
    target = gait_share(clip_smoothed_speed(pos, fps))
    out = np.zeros(len(target))
    for t in range(1, len(target)):
        out[t] = followed(out[t - 1 : t], target[t : t + 1], np.array([True]))[0]
    return out
