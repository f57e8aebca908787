"""While the input raises a hand, the output prior steps aside for the styles it misleads there.

The output prior (`rotation_prior.py`) maps the network's rotations toward a style onto the
style's real ones with one Gaussian per joint, fitted over every content at once, so a raised arm
is carried by a map that hanging and swinging arms dominate. Toward `elderly` that turned
raise-ups into waves: on the VALIDATION split the content judge read 2 of the 4 left-hand
raise-ups toward elderly as waves (the prior moved the raised hand out from the body and added a
sideways wobble), 4 of 4 right without the output prior, and elderly's rotation judge read all 21
raise-ups and waves as elderly either way (`out/s24/erd_gest.py`, scratch). Toward the other five
styles the prior is what their rotation judge reads on the raised arm (without it, 9-12 of the 21
for feminine, masculine and youthful, against 16-21 with it), so for them it stays.

So a frame's weight on the output prior of each style in `FADED_STYLES` falls off as the input
raises a hand: the share ramps with the higher hand's height above its shoulder (the UpperArm
joint) over `RAISE_RAMP_CM`, from the TRAIN `normal` runs' p99 (-12 cm: a running arm's swing
reaches past it in about 1 % of frames, its p99.9 3 cm past (a share of 0.25); the walks'
p99.9 is -21 to -25 cm) to the shoulder's height. What the fade takes away is the carry, not
the style's real range: the faded rows are still clamped into it at their full
weights (`kept_in_range`). Causal and per frame: it reads the input frame's own pose.

Chosen on validation (`python -m models.eval --split val --methods erd`; model card): elderly's
row passes there (content 88 -> 94 %, every other gate held; without the clamp its worst joint
fell 100 -> 98 %); fading every style passes feminine's content too but costs four styles'
rotation judge, and feminine's and masculine's arms leave their real p99. The ramp's ends were
not tuned: -20..0 cm and -12..+7 cm give the same validation rows.
"""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import HIPS
from ..motion.hands import hand_height, raise_share
from ..motion.style_carry import StyleCarry
from .dataset import TARGET_STYLES

FADED_STYLES = ("elderly",)
_FADED = np.array([TARGET_STYLES.index(s) for s in FADED_STYLES])


def output_prior_weights(weights: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(B, S) style weights for the output prior: `weights` with each faded style's weight
    scaled by 1 - the row's raise share (a zero weight carries nothing; `StyleCarry`). Where no
    row asks for a faded style, `weights` themselves (nothing to measure)."""
    w = np.asarray(weights, np.float64)
    if not w[..., _FADED].any():
        return w
    out = w.copy()
    out[..., _FADED] *= 1.0 - raise_share(hand_height(pos))[..., None]
    return out


def kept_in_range(prior: StyleCarry | None, q: np.ndarray, weights: np.ndarray, faded: np.ndarray) -> np.ndarray:
    """(B, J, 4) rotations `q` carried with the `faded` weights, clamped into `prior`'s range
    (`StyleCarry.bounds`) at the full `weights` where the fade took some of them: the fade
    drops what the prior carries, not the style's real range (the Hips without their heading)."""
    if prior is None or faded is weights:
        return q
    rows = np.any(np.asarray(faded) != np.asarray(weights), axis=-1)
    if not rows.any():
        return q
    out = np.array(q, np.float64)
    out[rows] = prior.clamped(out[rows], np.asarray(weights, np.float64)[rows], hips=HIPS)
    return out
