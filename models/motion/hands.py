"""What a hand does, measured causally on the Bandai Namco rig: how far it is raised above its
shoulder (`RAISE_RAMP_CM`), and how fast it sways (`WAVE_RAMP_CM_S`) and rises. LTI tells a
raise-up (raised, held still) from a wave (swaying at a level height) by these.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .bn_skeleton import BN_JOINTS
from .skeleton import Motion, Skeleton

RAISE_RAMP_CM = (-12.0, 0.0)
WAVE_RAMP_CM_S = (40.0, 60.0)
SWAY_FRAMES = 10.0  # the sway's exponential average: each frame moves it 1 / SWAY_FRAMES of the way to the new speed
_HANDS = np.array([BN_JOINTS.index("Hand_L"), BN_JOINTS.index("Hand_R")])
_SHOULDERS = np.array([BN_JOINTS.index("UpperArm_L"), BN_JOINTS.index("UpperArm_R")])


def hand_offsets(pos: np.ndarray) -> np.ndarray:
    """(..., 2, 3) each hand (left, right) from its own shoulder, from world joint positions (..., J, 3)."""
    return pos[..., _HANDS, :] - pos[..., _SHOULDERS, :]


def _arm_chain(skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joints from the root to each hand and shoulder, parents first; the hands; the shoulders)."""
    names = list(skeleton.names)
    hands = np.array([names.index(BN_JOINTS[h]) for h in _HANDS])
    shoulders = np.array([names.index(BN_JOINTS[s]) for s in _SHOULDERS])
    chain: set[int] = set()
    for j in (*hands, *shoulders):
        j = int(j)
        while j >= 0:
            chain.add(j)
            j = int(skeleton.parents[j])
    return np.array(sorted(chain)), hands, shoulders  # parents come before their children on the rig


class HandMeter:
    """The arm chains of `skeleton` for the compiled meter (`hands_kernels.hand_step`), set up once."""

    def __init__(self, skeleton: Skeleton) -> None:
        self.chain, self.hands, self.shoulders = _arm_chain(skeleton)
        self.parents = np.ascontiguousarray(skeleton.parents, np.int64)
        self.offsets = np.ascontiguousarray(skeleton.offsets, np.float64)


def raise_share(height: np.ndarray) -> np.ndarray:
    """(...,) how far each frame's hand is raised: 0 up to the ramp, 1 from the shoulder's height, linear between."""
    lo, hi = RAISE_RAMP_CM
    return np.minimum(np.maximum((np.asarray(height, np.float64) - lo) / (hi - lo), 0.0), 1.0)


def sway(
    before: np.ndarray, offsets: np.ndarray, prev_offsets: np.ndarray, has_prev: np.ndarray, fps: float
) -> np.ndarray:
    """(B, 2) each hand's averaged horizontal speed (cm/s) against its shoulder."""
    step = np.asarray(offsets)[..., ::2] - np.asarray(prev_offsets)[..., ::2]  # x and z
    speed = np.linalg.norm(step, axis=-1) * fps
    return np.where(has_prev[:, None], before + (speed - before) / SWAY_FRAMES, 0.0)


def _over_clip(average: Callable[..., np.ndarray], offsets: np.ndarray, fps: float) -> np.ndarray:
    out = np.zeros((len(offsets), 2))
    for t in range(1, len(offsets)):
        out[t] = average(out[t - 1 : t], offsets[t : t + 1], offsets[t - 1 : t], np.ones(1, bool), fps)[0]
    return out


def clip_sway(offsets: np.ndarray, fps: float) -> np.ndarray:
    """(T, 2) `sway` over every frame of a clip's `hand_offsets` (T, 2, 3), as a stream sees it."""
    return _over_clip(sway, offsets, fps)


def wave_share(swayed: np.ndarray) -> np.ndarray:
    """(..., 2) how much each hand waves: 0 up to `WAVE_RAMP_CM_S`, 1 from its end, linear between."""
    lo, hi = WAVE_RAMP_CM_S
    return np.clip((np.asarray(swayed, np.float64) - lo) / (hi - lo), 0.0, 1.0)


def calm_sides(motion: Motion) -> np.ndarray:
    """(T, 2) bool: frames with each hand raised and not waving."""
    offsets = hand_offsets(motion.global_positions())
    return (raise_share(offsets[..., 1]) > 0.5) & (wave_share(clip_sway(offsets, motion.fps)) < 0.5)


def calm_frames(motion: Motion, side: int) -> np.ndarray:
    """(T,) bool: `calm_sides` of the `side` hand (0: the left, 1: the right)."""
    return calm_sides(motion)[:, side]
