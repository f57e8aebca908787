"""The numpy reference of LTI's waving arm (`models/lti/waving_arm.py`, compiled in
`waving_kernels.swing_arms`): the same formulas on whole arrays, for the tests to compare with."""

from __future__ import annotations

import numpy as np

from models.lti.waving_arm import ARM, GAIN, TRACK_FRAMES
from models.motion.hands import LEVEL_RAMP_CM_S, RAISE_RAMP_CM, raise_share, wave_share
from models.motion.rotations import quat_exp, quat_inv, quat_log, quat_mul
from tests.reference.rotation_ball import clamp_rotations


def level_share(risen: np.ndarray) -> np.ndarray:
    """(..., 2) how level each hand is held: 1 up to `LEVEL_RAMP_CM_S` of `rise`, 0 from its end.
    A raise-up's hand also sways as it goes up (on the validation raise-ups the wave share
    reached 0.7-1.0 for about 13 frames of the rise); at a level one it does not."""
    lo, hi = LEVEL_RAMP_CM_S
    return 1.0 - np.clip((np.asarray(risen, np.float64) - lo) / (hi - lo), 0.0, 1.0)


def shares(offsets: np.ndarray, swayed: np.ndarray, risen: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(B, 2) how far each arm takes the input's swing: its hand's raise share times its wave
    share times its level share, from the input's `hand_offsets` (B, 2, 3), sway and rise (B, 2),
    times the style weights' total (B, S) up to 1 (at no style the output is the input's, swing
    and all)."""
    total = np.minimum(np.sum(weights, axis=-1), 1.0)[:, None]
    return raise_share(np.asarray(offsets)[..., 1]) * wave_share(swayed) * level_share(risen) * total


def _aligned(q: np.ndarray, to: np.ndarray) -> np.ndarray:
    """q with each quaternion's sign flipped where it lies on the far side of `to`'s."""
    return np.where(np.sum(q * to, axis=-1, keepdims=True) < 0.0, -q, q)


def tracked(mean: np.ndarray, q: np.ndarray, fresh: np.ndarray) -> np.ndarray:
    """(B, 2, J, 4) the running mean after this frame's rotations q (B, 2, J, 4): a normalised
    step of 1 / `TRACK_FRAMES` toward q; the sides where `fresh` (B, 2) start at q."""
    step = mean + (_aligned(q, mean) - mean) / TRACK_FRAMES
    out = np.where(fresh[..., None, None], q, step)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def fresh_sides(started: np.ndarray, prev_offsets: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """(B, 2) the sides whose running means start again this frame: a session's first frame, a
    hand that was below its raise ramp the frame before, and a mean never set (all zeros: a
    snapshot from before the waving arm)."""
    below = np.asarray(prev_offsets)[..., 1] <= RAISE_RAMP_CM[0]
    return ~np.asarray(started, bool)[:, None] | below | ~np.any(mean != 0.0, axis=(-2, -1))


def held(
    rotations: np.ndarray, joints: np.ndarray, weights: np.ndarray, means: np.ndarray, radii: np.ndarray
) -> np.ndarray:
    """(B, len(joints), 4) `joints` of `rotations` (B, J, 4) held inside each style's rotation
    ball (means (S, J, 4), radii (S, 2, J)) and blended by the style weights (B, S, every row's
    sum > 0): what the translator's own step does with every joint (`kernels.lti_step`)."""
    share = weights / np.sum(weights, axis=-1, keepdims=True)
    acc = np.zeros((len(rotations), len(joints), 4))
    for s in np.flatnonzero(np.any(weights > 0.0, axis=0)):
        clamped = clamp_rotations(rotations, means[s], radii[s])[:, joints]
        acc += share[:, s, None, None] * _aligned(clamped, rotations[:, joints])
    return acc / np.linalg.norm(acc, axis=-1, keepdims=True)


def swung(
    out_rot: np.ndarray,
    in_rot: np.ndarray,
    out_mean: np.ndarray,
    in_mean: np.ndarray,
    share: np.ndarray,
    weights: np.ndarray,
    means: np.ndarray,
    radii: np.ndarray,
) -> np.ndarray:
    """(B, J, 4) the output rotations `out_rot` with each side's arm turned from the output's
    running mean `out_mean` by `GAIN` times the input's (`in_rot`) rotation from its running
    mean `in_mean` (both (B, 2, 2, 4), this frame's), mixed in by that side's `share` (B, 2,
    `shares`) and held inside the styles' balls (`held`). A side without a share is left as it
    was. The numpy reference of `waving_kernels.swing_arms`."""
    out = out_rot
    for side in (0, 1):
        rows = np.flatnonzero(share[:, side] > 0.0)
        if rows.size == 0:
            continue
        if out is out_rot:
            out = np.array(out_rot, np.float64, copy=True)
        joints = ARM[side]
        a = out[np.ix_(rows, joints)]
        swing = quat_log(quat_mul(quat_inv(in_mean[rows, side]), in_rot[np.ix_(rows, joints)]))
        target = _aligned(quat_mul(out_mean[rows, side], quat_exp(GAIN * swing)), a)
        s = share[rows, side][:, None, None]
        mixed = (1.0 - s) * a + s * target
        out[np.ix_(rows, joints)] = mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)
        out[np.ix_(rows, joints)] = held(out[rows], joints, weights[rows], means, radii)
    return out
