"""Which of a style's clips run, measured from the clips, so an uploaded style gets the split its
built-in peers get. No fixed speed works (elderly runs are slower than active walks): the moving
clips' median speeds are split by Otsu's method in 1-D, one gait unless `SEPARATION` apart.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .skeleton import Motion

MOVING_CM_S = 40.0  # a clip whose median Hips speed is under this stands (gestures): no gait
SEPARATION = 1.5  # the faster group's mean speed over the slower's, for two gaits


def clip_speed(motion: Motion) -> float:
    """Median horizontal Hips speed (cm/s) of a `Motion` (joint 1 is the Hips on every rig here)."""
    step = np.diff(np.asarray(motion.translations, np.float64)[:, 1][:, [0, 2]], axis=0)
    return float(np.median(np.linalg.norm(step, axis=1)) * motion.fps) if len(step) else 0.0


def two_groups(values: Sequence[float], separation: float = SEPARATION) -> float:
    """Otsu's 1-D split of `values`; infinite for one group or groups under `separation` apart."""
    v = np.sort(np.asarray(values, np.float64))
    if len(v) < 2:
        return float("inf")
    cost = [np.var(v[:k]) * k + np.var(v[k:]) * (len(v) - k) for k in range(1, len(v))]
    k = int(np.argmin(cost)) + 1
    slow, fast = v[:k], v[k:]
    if fast.mean() < separation * slow.mean():
        return float("inf")
    return float(0.5 * (slow[-1] + fast[0]))


def run_threshold(speeds: Sequence[float]) -> float:
    """The median Hips speed above which this style's clips run; infinite for one gait."""
    return two_groups([s for s in speeds if s >= MOVING_CM_S])


def running(speeds: Sequence[float]) -> np.ndarray:
    """(N,) bool: which of one style's clips, with these median Hips speeds, run (`run_threshold`)."""
    return np.asarray(speeds, np.float64) > run_threshold(speeds)


def split_by_gait(motions: list) -> tuple[list, list]:
    """(walking, running) clips of one style; standing clips (under `MOVING_CM_S`) in neither."""
    speeds = [clip_speed(m) for m in motions]
    cut = run_threshold(speeds)
    walking = [m for m, s in zip(motions, speeds) if MOVING_CM_S <= s <= cut]
    return walking, [m for m, s in zip(motions, speeds) if s > cut]
