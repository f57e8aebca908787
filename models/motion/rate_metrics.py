"""How smoothly a stream is served at its own frame rate (`models.motion.rate`), output against
input: rotation jitter and planted-foot slide (sample-and-hold shows both), and timing lag (a
smoothing filter shows that).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .rotations import quat_inv, quat_log, quat_mul
from .skeleton import Motion


def rotation_acceleration(rotations: np.ndarray, fps: float) -> np.ndarray:
    """(T - 2, J) rad/s^2: the change of each joint's per-frame rotation vector, times fps^2."""
    q = np.asarray(rotations, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    step = quat_log(quat_mul(quat_inv(q[:-1]), q[1:]))  # (T - 1, J, 3), shortest path
    return np.linalg.norm(np.diff(step, axis=0), axis=-1) * fps * fps


def jitter(rotations: np.ndarray, fps: float, joints: np.ndarray | None = None) -> float:
    """p99 rotation acceleration (rad/s^2) over frames and `joints` (default: all)."""
    acc = rotation_acceleration(rotations, fps)
    acc = acc if joints is None else acc[:, joints]
    return float(np.percentile(acc, 99)) if acc.size else 0.0


def _continuous(rotations: np.ndarray) -> np.ndarray:
    """Quaternions with signs flipped so each joint's track is continuous over time."""
    q = np.asarray(rotations, float).copy()
    for t in range(1, len(q)):
        flip = np.sum(q[t] * q[t - 1], axis=-1) < 0
        q[t, flip] *= -1
    return q


def lag_frames(reference: np.ndarray, delayed: np.ndarray, max_lag: int) -> float:
    """The shift (frames) best aligning two rotation tracks, by cross-correlation."""
    a, b = _continuous(reference), _continuous(delayed)
    n = min(len(a), len(b))
    a = (a[:n] - a[:n].mean(0)).reshape(n, -1)
    b = (b[:n] - b[:n].mean(0)).reshape(n, -1)
    lags = np.arange(-max_lag, max_lag + 1)
    scores = np.empty(len(lags))
    for i, lag in enumerate(lags):
        x, y = (a[: n - lag], b[lag:]) if lag >= 0 else (a[-lag:], b[: n + lag])
        scores[i] = float(np.sum(x * y)) / max(len(x), 1)
    i = int(np.argmax(scores))
    if 0 < i < len(lags) - 1:
        left, mid, right = scores[i - 1 : i + 2]
        curve = left - 2 * mid + right
        if curve < 0:
            return float(lags[i] + 0.5 * (left - right) / curve)
    return float(lags[i])


def planted_slide_p95(motion: Motion, root_joint: int, root: np.ndarray, rotations: np.ndarray) -> float:
    """p95 speed (leg lengths/s) of flat planted feet of `motion`'s skeleton posed by `root`, `rotations`."""
    from ..eval.metrics import flat_foot_contacts, planted
    from .features import left_leg_length

    translations = motion.translations[: len(root)].copy()
    translations[:, root_joint] = root
    posed = replace(motion, rotations=np.asarray(rotations, float), translations=translations)
    speeds = planted(*flat_foot_contacts(posed))
    return float(np.percentile(speeds, 95)) / left_leg_length(motion.skeleton) if len(speeds) else 0.0
