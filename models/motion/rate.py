"""Serving a stream at its own frame rate while the model steps at its own (30 fps).

Why: sample-and-hold (one model step per model period, the frames between holding that pose
while the root moved on) left a 120 fps stream with a pose updated every 4th frame and planted
feet that glide, then snap. Here, with no look-ahead:

- the model steps at its own times T_j = j / model_fps, each on the input pose at T_j,
  interpolated from the two input frames around it (the second one has just arrived);
- each input frame at time t gets the model's output at t - delay, root and pose at that one
  instant (planted feet stay planted), on the parabola through the three latest model outputs
  (each joint's in the tangent space of the middle one). A parabola, not a straight line: a
  straight line between outputs turns at each one, which at 120 fps showed as rotation
  acceleration spikes (p99 1.6x the input's on a CMU walk, 1.3x with the parabola); the curve
  still passes through every model output, so nothing is smoothed away.

The delay is the least that keeps that instant between the two latest model steps for every
frame: (b - 1) / b model frames, where model_fps / fps = a / b in lowest terms (0 at 30 fps,
1/2 at 60, 3/4 at 120 and 24); one model frame when the ratio is not a small fraction.

Everything is row-batched, (n, ...) arrays, one row per stream: a session is one row, a crowd's
characters many, and both get the same arithmetic bit for bit. A stream's rate state is its
`clock` (how far its latest input frame lies past its latest model step, in model frames; < 0
before its first frame), its latest input frame and its `HISTORY` latest model outputs.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from .resample import slerp

EPS = 1e-9
HISTORY = 3  # model outputs kept: the parabola's three points


def output_lag(model_fps: float, fps: float) -> float:
    """The output's fixed delay behind the input, in model frames (in [0, 1])."""
    ratio = model_fps / fps
    frac = Fraction(ratio).limit_denominator(240)
    if abs(float(frac) - ratio) > 1e-12:
        return 1.0
    return (frac.denominator - 1) / frac.denominator


def output_delay_s(model_fps: float, fps: float) -> float:
    """`output_lag` in seconds."""
    return output_lag(model_fps, fps) / model_fps


def steps_due(clock: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For one new input frame per row: (new clock, model steps due (n,), weights (n, max steps)).

    `ratio` is model_fps / fps. Weight k of a row places its k-th step between the row's previous
    input frame (0) and this one (1). A row's first frame (clock < 0) steps once, on itself."""
    first = clock < 0
    moved = np.where(first, 0.0, clock + ratio)
    steps = np.where(first, 1, np.floor(moved + EPS).astype(np.int64))
    count = int(steps.max(initial=0))
    m = np.arange(1, count + 1, dtype=float)[None, :]
    weights = np.where(first[:, None], 1.0, (m - clock[:, None]) / ratio)
    weights = np.clip(weights, 0.0, 1.0)
    weights[weights > 1.0 - EPS] = 1.0
    return np.where(first, 0.0, moved - steps).clip(min=0.0), steps, weights


def blend(
    root0: np.ndarray, rot0: np.ndarray, root1: np.ndarray, rot1: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of (root, rotations) a fraction `w` (n,) of the way from pose 0 to pose 1: roots
    lerped, each joint slerped; w == 1 gives pose 1 exactly and w == 0 pose 0 (copies)."""
    w = np.asarray(w, float)
    root = root0 + w[:, None] * (root1 - root0)
    rot = np.array(rot1, dtype=float, copy=True)
    root[w == 1.0] = root1[w == 1.0]
    between = (w > 0.0) & (w < 1.0)
    if between.any():
        rot[between] = slerp(rot0[between], rot1[between], w[between, None, None])
    rot[w == 0.0] = rot0[w == 0.0]
    return root, rot


def output_weight(clock: np.ndarray, lag: float) -> np.ndarray:
    """Where each row's output instant (its input time less the delay) lies between its
    second-latest model output (0) and its latest (1)."""
    return np.clip(clock - lag + 1.0, 0.0, 1.0)


def push(history: np.ndarray, latest: np.ndarray) -> np.ndarray:
    """(n, HISTORY, ...) outputs, oldest first, with `latest` (n, ...) added (a new array)."""
    return np.concatenate([history[:, 1:], latest[:, None]], axis=1)


def log_quat(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) -> rotation vectors (..., 3), the shorter way round."""
    q = np.where(q[..., 3:] < 0, -q, q)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:])
    return q[..., :3] * np.where(s < 1e-12, 2.0, angle / np.maximum(s, 1e-300))


def exp_quat(v: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) -> unit quaternions (..., 4)."""
    half = 0.5 * np.linalg.norm(v, axis=-1, keepdims=True)
    scale = np.where(half < 1e-12, 0.5, np.sin(half) / np.maximum(2.0 * half, 1e-300))
    return np.concatenate([v * scale, np.cos(half)], axis=-1)


def interpolate(roots: np.ndarray, rotations: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows' (root, rotations) at `u` (n,) between their second-latest output (0) and latest (1)
    on the parabola through their three latest: roots (n, 3, 3), rotations (n, 3, J, 4), oldest
    first. u == 1 gives the latest output exactly (every frame at 30 fps)."""
    from .rotations import quat_inv, quat_mul

    u = np.asarray(u, float)
    root = np.array(roots[:, 2], dtype=float, copy=True)
    rot = np.array(rotations[:, 2], dtype=float, copy=True)
    between = u < 1.0
    if between.any():
        x = u[between]
        before, now, after = x * (x - 1.0) / 2.0, 1.0 - x * x, x * (x + 1.0) / 2.0
        r = roots[between]
        root[between] = before[:, None] * r[:, 0] + now[:, None] * r[:, 1] + after[:, None] * r[:, 2]
        q = rotations[between]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        base = q[:, 1]
        inv = quat_inv(base)
        tangent = before[:, None, None] * log_quat(quat_mul(inv, q[:, 0])) + after[:, None, None] * log_quat(
            quat_mul(inv, q[:, 2])
        )
        rot[between] = quat_mul(base, exp_quat(tangent))
    return root, rot
