"""Style-ERD's rotation stages in numpy: the references their compiled kernels
(`models/motion/style_carry_kernels.py`, `models/erd/kernels.py`) are tested against."""

from __future__ import annotations

import numpy as np

from models.erd.gait import carry_by_gait
from models.erd.slow_carry import carry_slow as compiled_carry_slow
from models.erd.slow_carry import follow
from models.erd.twist_range import TwistRange
from models.motion.bn_skeleton import HIPS
from models.motion.rotation_ball import split_heading
from models.motion.rotations import quat_exp, quat_inv, quat_log, quat_mul, twist_angle
from models.motion.style_carry import StyleCarry

from .style_carry import style


def apply(carry: StyleCarry, q: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`carry(q, weights)` in numpy. Only the (row, style) pairs with a weight are computed, so a
    batch of single styles costs one carry per row."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)  # the data's quaternions are unit to ~1e-7
    w = np.asarray(weights, np.float64)
    rows, styles = np.nonzero(w)
    if len(rows) == 0:
        return q.copy()
    correction = np.zeros(q.shape[:-1] + (3,))
    for s in np.unique(styles):
        r = rows[styles == s]
        fs = style(carry, q[r], int(s))
        np.add.at(correction, r, w[r, s][:, None, None] * quat_log(quat_mul(quat_inv(q[r]), fs)))
    return quat_mul(q, quat_exp(correction))


def carry_output(prior: StyleCarry, rot: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`prior(rot, weights, hips=HIPS)` in numpy: the output prior, the Hips carried without their heading."""
    heading, free = split_heading(rot)
    out = apply(prior, free, weights)
    out[:, HIPS] = quat_mul(heading, out[:, HIPS])
    return out


def carry_slow(
    other: StyleCarry | None,
    run: StyleCarry | None,
    q: np.ndarray,
    slow: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
) -> tuple[np.ndarray, np.ndarray]:
    """`models.erd.slow_carry.carry_slow` in numpy (the carry itself by `gait.carry_by_gait`)."""
    new = follow(slow, q)
    if other is None and run is None:
        return q, new
    w = np.asarray(weights, np.float64)
    carried = carry_by_gait(other, run, new, w, share, hips=hips)
    q = np.asarray(q, np.float64)
    fast = quat_mul(quat_inv(new), q / np.linalg.norm(q, axis=-1, keepdims=True))
    fast = np.where(fast[..., 3:] < 0.0, -fast, fast)
    if other is None:  # a run prior alone (no range to clamp into): the fast part as it is
        return quat_mul(carried, fast), new
    g = np.einsum("bs,sjik->bjik", w, other.damping)
    g += np.maximum(1.0 - w.sum(1), 0.0)[:, None, None, None] * np.eye(3)
    if hips >= 0:
        g[:, hips] = np.eye(3)
    fast = np.concatenate([np.einsum("bjik,bjk->bji", g, fast[..., :3]), fast[..., 3:]], axis=-1)
    out = other.bounds(quat_mul(carried, fast / np.linalg.norm(fast, axis=-1, keepdims=True)), w, hips=hips)
    plain = other.clamps_only  # nothing to carry slowly: carried whole
    out[:, plain] = carry_by_gait(other, run, q, w, share, hips=hips)[:, plain]
    return out, new


def twist_clamp(twists: TwistRange, q: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`twists(q, weights)` in numpy."""
    w = np.asarray(weights, np.float64)
    rows = np.flatnonzero(w.any(axis=1))
    if len(rows) == 0:
        return q
    arms = np.asarray(q, np.float64)[rows][:, twists.joints]  # (R, K, 4)
    t = twist_angle(quat_mul(quat_inv(twists.mean)[None], arms[:, None]), twists.axes)  # (R, S, K)
    delta = np.einsum("rs,rsk->rk", w[rows], np.clip(t, twists.lo, twists.hi) - t)
    half = 0.5 * delta[..., None]
    turn = np.concatenate([np.sin(half) * twists.axes, np.cos(half)], axis=-1)  # about each bone
    out = np.array(q, np.float64)
    out[np.ix_(rows, twists.joints)] = quat_mul(arms, turn)
    return out


def clip_carry_slow(
    other: StyleCarry | None,
    run: StyleCarry | None,
    q: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
) -> np.ndarray:
    """The compiled `carry_slow` over every frame (T, J, 4) of a clip, each frame's slow copy
    followed in numpy, as a stream sees it."""
    before = np.zeros_like(np.asarray(q, np.float64))  # each frame's slow copy before it
    for t in range(1, len(q)):
        before[t] = follow(before[t - 1 : t], q[t - 1 : t])[0]
    return compiled_carry_slow(other, run, q, before, weights, share, hips)[0]
