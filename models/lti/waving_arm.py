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
from ..motion.hands import LEVEL_RAMP_CM_S, RAISE_RAMP_CM, WAVE_RAMP_CM_S
from .waving_kernels import WavingArm

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
