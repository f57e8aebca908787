"""The hands' offsets from their shoulders and the sway step, compiled (numba): per-row FK over the
arm chains (numpy reference: `tests/reference/hands.py`), microseconds instead of ~0.45 ms."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from .quaternion import qmul, qrot, quat_at, qunit, row3, row4


class Hands(NamedTuple):
    """A rig's arm chains and the meter's settings (`hands.HandMeter`)."""

    parents: np.ndarray  # (J,) int64
    offsets: np.ndarray  # (J, 3)
    chain: np.ndarray  # joints from the root to the hands and shoulders, parents first
    hands: np.ndarray  # (2,) int64
    shoulders: np.ndarray  # (2,) int64
    fps: float
    frames: float  # the sway's and rise's exponential average
    above: float  # a hand higher than this over its shoulder is on its raise ramp


@njit(cache=True, error_model="numpy")
def hand_step(rot, rig, prev, before, rise_before, started, out, swayed, risen):
    """Per row: each hand's offset from its shoulder into out, its averaged sway and rise; returns whether
    any hand is higher than `above`."""
    parents, offsets, chain, hands, shoulders, fps, frames, above = rig
    J = rot.shape[1]
    g = np.empty((J, 4))
    p = np.empty((J, 3))
    raised = False
    for b in range(rot.shape[0]):
        has_prev = False
        if started[b]:
            for s in range(2):
                for k in range(3):
                    if prev[b, s, k] != 0.0:
                        has_prev = True
        for j in chain:
            u = qunit(quat_at(rot, b, j))
            a = parents[j]
            if a < 0:
                g[j, 0], g[j, 1], g[j, 2], g[j, 3] = u
                p[j, 0], p[j, 1], p[j, 2] = 0.0, 0.0, 0.0
            else:
                ga = row4(g, a)
                g[j, 0], g[j, 1], g[j, 2], g[j, 3] = qmul(ga, u)
                ox, oy, oz = qrot(ga, row3(offsets, j))
                p[j, 0], p[j, 1], p[j, 2] = p[a, 0] + ox, p[a, 1] + oy, p[a, 2] + oz
        for s in range(2):
            for k in range(3):
                out[b, s, k] = p[hands[s], k] - p[shoulders[s], k]
            if out[b, s, 1] > above:
                raised = True
            if has_prev:
                dx, dz = out[b, s, 0] - prev[b, s, 0], out[b, s, 2] - prev[b, s, 2]
                speed = math.sqrt(dx * dx + dz * dz) * fps
                swayed[b, s] = before[b, s] + (speed - before[b, s]) / frames
                vertical = abs(out[b, s, 1] - prev[b, s, 1]) * fps
                risen[b, s] = rise_before[b, s] + (vertical - rise_before[b, s]) / frames
            else:
                swayed[b, s] = 0.0
                risen[b, s] = 0.0
    return raised
