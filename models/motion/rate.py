"""Serving a stream at its own frame rate while the model steps at 30 fps.

Sample-and-hold would make planted feet glide, then snap. Instead the model steps at its own
times on the input interpolated there, and each input frame gets the output `delay` earlier on the
parabola through the three latest outputs (a line would spike rotation acceleration at each one).
The delay is the least keeping that instant between the two latest steps: (b - 1) / b model frames
for model_fps / fps = a / b in lowest terms, one model frame when the ratio is not small.

Row-batched, one row per stream. A stream's state is its `clock` (its latest input frame past its
latest step, in model frames; < 0 before the first), latest input frame and `HISTORY` outputs.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from .rate_kernels import blend_rows, interpolate_rows

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
    return output_lag(model_fps, fps) / model_fps


def steps_due(clock: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row for one new input frame: (new clock, steps due, each step's place between the frames)."""
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
    """Rows of (root, rotations) `w` of the way from pose 0 to pose 1 (lerp, slerp; exact at 0 and 1)."""
    root1, rot1 = _f64(root1), _f64(rot1)
    out_root, out_rot = np.empty_like(root1), np.empty_like(rot1)
    blend_rows(_f64(root0), _f64(rot0), root1, rot1, _f64(w), out_root, out_rot)
    return out_root, out_rot


def output_weight(clock: np.ndarray, lag: float) -> np.ndarray:
    """Where each row's output instant lies between its second-latest (0) and latest (1) output."""
    return np.clip(clock - lag + 1.0, 0.0, 1.0)


def push(history: np.ndarray, latest: np.ndarray) -> np.ndarray:
    """(n, HISTORY, ...) outputs, oldest first, with `latest` (n, ...) added (a new array)."""
    return np.concatenate([history[:, 1:], latest[:, None]], axis=1)


def interpolate(roots: np.ndarray, rotations: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows' (root, rotations) at `u` on the parabola through their three latest outputs (u == 1: latest)."""
    roots, rotations = _f64(roots), _f64(rotations)
    out_root, out_rot = np.empty_like(roots[:, 0]), np.empty_like(rotations[:, 0])
    interpolate_rows(roots, rotations, _f64(u), out_root, out_rot)
    return out_root, out_rot


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)
