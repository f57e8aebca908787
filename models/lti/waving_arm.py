"""A waving hand keeps its wave: the input's swing carried onto the translated arm.

Why: the translators damp a wave's swing. They are linear maps identified over every content,
walks most of all, and fitted as if their inputs were noisy (`train.py`, `context_noise`), which
shrinks their gains; a wave's arm lies far from where they were fitted.

What: each arm's UpperArm and LowerArm rotation is read as a running mean (an exponential average
over `TRACK_FRAMES`, restarted each time the hand comes up) and the rotation from it. While the
input's hand is raised, waving and level (`models.motion.hands`: raise x wave x level shares),
the output joint is turned from its own running mean by `GAIN` times the input's rotation from
its running mean, mixed in by the share, then held inside the target style's rotation ball
(`models.motion.rotation_ball`), so the swing never leaves what the style's real data shows. The
pose where the arm is held is the model's; the swing about it is the input's. A raised hand that
holds still is `raised_arm.py`'s; a hand below its raise ramp is left as the translator made it.
`GAIN`, the joints and `TRACK_FRAMES` were chosen on the validation clips (model card).
"""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import BN_JOINTS
from ..motion.hands import LEVEL_RAMP_CM_S, RAISE_RAMP_CM, WAVE_RAMP_CM_S, clip_rise
from .waving_kernels import WavingArm, swing_batch

JOINTS = ("UpperArm", "LowerArm")
TRACK_FRAMES = 15.0  # the running mean's exponential average: each frame moves it 1 / TRACK_FRAMES of the way
GAIN = 1.3  # the input's swing, scaled
ARM = np.array([[BN_JOINTS.index(f"{j}_{side}") for j in JOINTS] for side in "LR"])  # (2 sides, 2 joints)
MEAN_SHAPE = (2, len(JOINTS), 4)  # a session's running mean of each side's joints


def settings() -> WavingArm:
    """The record the compiled step takes (`waving_kernels.WavingArm`)."""
    return WavingArm(
        ARM,
        np.array(RAISE_RAMP_CM, np.float64),
        np.array(WAVE_RAMP_CM_S, np.float64),
        np.array(LEVEL_RAMP_CM_S, np.float64),
        TRACK_FRAMES,
        GAIN,
    )


def step(*arrays: np.ndarray, swing: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame for every row (`waving_kernels.swing_arms`) from `arrays`: the input's and the
    output's rotations (B, J, 4), the style weights (B, S), whether each row has started, the
    input's `hand_offsets` before and now (B, 2, 3), its sway and rise (B, 2), the running means
    before (B, 2, 2, 4) and the styles' balls (means (S, J, 4), radii (S, 2, J)). Returns the
    output rotations with the waving arms swung (a copy) and the running means after this frame."""
    out = np.array(arrays[1], np.float64, copy=True)
    new_in, new_out = np.empty((len(out), *MEAN_SHAPE)), np.empty((len(out), *MEAN_SHAPE))
    inputs = (arrays[0], out, *arrays[2:])
    args = (tuple(settings()), *(np.ascontiguousarray(a, np.float64) for a in inputs), swing, new_in, new_out)
    swing_batch(*args)
    return out, new_in, new_out


def clip(
    out_rots: np.ndarray,
    in_rots: np.ndarray,
    offsets: np.ndarray,
    swayed: np.ndarray,
    fps: float,
    means: np.ndarray,
    radii: np.ndarray,
) -> np.ndarray:
    """(T, J, 4) a whole clip's output rotations of one style (balls means (1, J, 4), radii
    (1, 2, J)) with its waving arms swung, frame by frame as a stream does (`step`), from the
    input's rotations, `hand_offsets` (T, 2, 3) and their `clip_sway` (T, 2)."""
    out = np.array(out_rots, np.float64, copy=True)
    risen = clip_rise(offsets, fps)
    in_mean, out_mean = np.zeros((1, *MEAN_SHAPE)), np.zeros((1, *MEAN_SHAPE))
    one = np.ones((1, 1))
    for t in range(len(out)):
        now, prev = slice(t, t + 1), slice(max(t - 1, 0), max(t, 1))
        rows = (in_rots[now], out[now], one, np.array([t > 0]), offsets[prev], offsets[now], swayed[now], risen[now])
        frame, in_mean, out_mean = step(*rows, in_mean, out_mean, means, radii)
        out[t] = frame[0]
    return out
