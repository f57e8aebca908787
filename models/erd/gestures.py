"""While the input raises a hand, the arms take output priors fitted on frames where the real
body does the same, for every style.

The output prior (`rotation_prior.py`) is fitted over every frame at once, so a raised arm is
carried by maps that hanging and swinging arms dominate: it moved raised hands out from the body
and added a sideways wobble, and the content judge read raise-ups as waves. So what the hand does,
measured from the input motion frame by frame, picks a prior fitted on the real frames where a
hand does the same (`rotation_prior.fit_arm_priors`, the same fit for every style):

- a hand that **waves** (sways sideways against its shoulder) takes the prior fitted on the
  frames with a raised hand waving (`output_prior_gesture.npz`), mixed in by the raise share
  (`models.motion.hands.raise_share`) times the wave share, at most `GESTURE_SHARE`;
- a hand raised **and still** puts its arm (`ARM_JOINTS`) on the prior fitted on that side's
  raised, still arms (`output_prior_raise.npz`), by the raise share times the still share;
- the **other, hanging** arm, while one hand is up, takes the prior fitted on that side's arm
  hanging while the other hand is raised (`output_prior_hanging.npz`), by the raised hand's share
  times the share this one is not raised. The real hanging arm keeps within a few degrees of its
  mean; the all-content maps, fitted mostly on swinging arms, spread it wider.

The sway is each hand's horizontal speed relative to its shoulder (the UpperArm joint), averaged
over `models.motion.hands.SWAY_FRAMES`: a raise-up's raised hand sways at a median of 21-34 cm/s,
a wave's at 57-96. Causal: the step from the previous input frame; a session's first frame has no
sway. A row with no style weight, and every row with both hands down, is carried as before.
The three priors' gains are capped at 1 (`rotation_prior.fit_arm_priors`): they move an arm's
pose toward the style's and keep it in range, but never magnify its motion (a magnified sway made
raise-ups read as waves).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..motion.bn_skeleton import BN_JOINTS
from ..motion.hands import raise_share, side_heights, still_share, wave_share
from ..motion.style_carry import StyleCarry

SIDES = "LR"  # the two arms, in the order `side_heights` gives them
GESTURE_SHARE = 0.5  # a fully waving hand's share of the gesture prior (the rest: the all-content prior)
ARM_JOINTS = ("Shoulder", "UpperArm", "LowerArm", "Hand")  # an arm's joints the raise and hanging priors carry
_ARM = [np.array([BN_JOINTS.index(f"{j}_{side}") for j in ARM_JOINTS]) for side in SIDES]

# (rows, their weights, a prior and its share per row, or None) -> those rows' rotations carried
# by the output prior, with that prior in the run prior's place by that share (None: the run
# prior by the gait, as the step carries every row)
Carry = Callable[[np.ndarray, np.ndarray, "tuple[StyleCarry, np.ndarray] | None"], np.ndarray]


@dataclass(frozen=True)
class ArmPriors:
    """The output priors a raised hand switches to (fitted by `rotation_prior.py`): a waving
    hand's row (`output_prior_gesture.npz`), a still raised arm (`output_prior_raise.npz`) and
    the other, hanging arm (`output_prior_hanging.npz`)."""

    waving: StyleCarry
    raised: StyleCarry | None = None
    hanging: StyleCarry | None = None


def _arm_by(out: np.ndarray, carry: Carry, prior: StyleCarry, w: np.ndarray, shares: np.ndarray) -> None:
    """Each side's `ARM_JOINTS` in `out` re-carried with `prior` at that side's share (B, 2), on
    the rows where it is above 0."""
    for side, joints in enumerate(_ARM):
        rows = np.flatnonzero(shares[:, side] > 0.0)
        if rows.size:
            out[np.ix_(rows, joints)] = carry(rows, w[rows], (prior, shares[rows, side]))[:, joints]


def by_gesture(
    carried: np.ndarray, carry: Carry, weights: np.ndarray, pos: np.ndarray, swayed: np.ndarray, arms: ArmPriors
) -> np.ndarray:
    """(B, J, 4) the output prior's result `carried`, with the rows that weigh a style re-carried
    where the input (world positions `pos`, hand sway `swayed` (B, 2)) raises a hand: a waving
    hand's row by `carry` with `arms.waving` at the raise share times the wave share (the larger
    hand's) times `GESTURE_SHARE`; a still raised hand's arm with `arms.raised` at its raise
    share times its still share; the other arm with `arms.hanging` at the raised hand's share
    times the share it is not raised itself."""
    w = np.asarray(weights, np.float64)
    styled = np.asarray(w.any(-1), bool)
    if not styled.any():
        return carried
    heights = raise_share(side_heights(pos)) * styled[:, None]  # (B, 2)
    if not heights.any():
        return carried
    out = np.array(carried, np.float64)
    waving = (heights * wave_share(swayed)).max(-1) * GESTURE_SHARE
    rows = np.flatnonzero(waving > 0.0)
    if rows.size:
        out[rows] = carry(rows, w[rows], (arms.waving, waving[rows]))
    if arms.raised is not None:
        _arm_by(out, carry, arms.raised, w, heights * still_share(swayed))
    if arms.hanging is not None:
        _arm_by(out, carry, arms.hanging, w, heights[:, ::-1] * (1.0 - heights))
    return out
