"""Style-ERD's rotation stages in numpy: the references their compiled kernels
(`models/motion/style_carry_kernels.py`, `models/erd/kernels.py`) are tested against."""

from __future__ import annotations

import numpy as np

from models.erd.slow_carry import SLOW_WEIGHT, SlowPrior
from models.erd.twist_range import TwistRange
from models.motion.assets import bandai_namco_skeleton
from models.motion.bn_skeleton import HIPS
from models.motion.rotation_ball import split_heading
from models.motion.rotations import quat_exp, quat_inv, quat_log, quat_mul, twist_angle
from models.motion.style_carry import StyleCarry
from models.stages import StageFrame

from .style_carry import style


def carry_by_gait(
    other: StyleCarry | None,
    run: StyleCarry | None,
    q: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
    stand: StyleCarry | None = None,
) -> np.ndarray:
    """Rotations (B, J, 4) carried by the all-content prior `other` and by the `run` prior (rows
    of share > 0) or the `stand` prior (share < 0) followed by a clamp into `other`'s range, mixed
    by each row's |share| (`StyleCarry.mixed_with`): share 0 is exactly `other` alone. Any prior
    may be None (without a gait's prior, `other` takes its rows). A row's result never depends on
    the others."""
    w = np.asarray(weights, np.float64)
    r = np.asarray(share, np.float64)
    out = np.array(q if other is None else other(q, w, hips=hips), np.float64)
    for gait, rows in ((run, r > 0.0), (stand, r < 0.0)):
        if gait is None or not rows.any():
            continue
        x, wr, k = np.asarray(q, np.float64)[rows], w[rows], np.abs(r[rows])
        out[rows] = (
            gait(x, wr * k[:, None], hips=hips)
            if other is None
            else other.mixed_with(gait, other.bounds, x, wr, k, hips=hips)
        )
    return out


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


def follow(slow: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(B, J, 4) the slow copy after this frame's rotations `q`: an exponential average by
    normalised lerp on the shorter arc. A row of zeros (a session's first frame) starts at `q`."""
    slow, q = np.asarray(slow, np.float64), np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    aligned = np.where(np.sum(slow * q, axis=-1, keepdims=True) < 0.0, -slow, slow)
    mixed = (1.0 - SLOW_WEIGHT) * aligned + SLOW_WEIGHT * q
    mixed /= np.maximum(np.linalg.norm(mixed, axis=-1, keepdims=True), 1e-12)
    unset = ~np.any(slow != 0.0, axis=(-1, -2))
    return np.where(unset[..., None, None], q, mixed)


def compiled_carry_slow(
    other: StyleCarry,
    run: StyleCarry | None,
    q: np.ndarray,
    slow: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
    stand: StyleCarry | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The compiled stage (`SlowPrior`) of these carries: the rotations carried and the new slow copies."""
    stage = SlowPrior(tuple(f"s{k}" for k in range(len(other.mean))), other, run, hips, stand=stand)
    rows = stage.rows(stage.styles, bandai_namco_skeleton())
    frame = StageFrame(np.asarray(q, np.float64), np.asarray(weights, np.float64), np.asarray(share, np.float64), -1)
    out, state = stage.step_batch({"slow": np.asarray(slow, np.float64)}, frame, rows)
    return out, state["slow"]


def twist_stage(twists: TwistRange, q: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The compiled stage (`TwistRange`) on rotations q and weights."""
    frame = StageFrame(np.asarray(q, np.float64), np.asarray(weights, np.float64), np.zeros(len(q)), -1)
    return twists.step_batch({}, frame, twists.rows(twists.styles, bandai_namco_skeleton()))[0]


def carry_slow(
    other: StyleCarry | None,
    run: StyleCarry | None,
    q: np.ndarray,
    slow: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
    stand: StyleCarry | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`compiled_carry_slow` in numpy (the carry itself by `carry_by_gait`)."""
    new = follow(slow, q)
    if other is None and run is None:
        return q, new
    w = np.asarray(weights, np.float64)
    carried = carry_by_gait(other, run, new, w, share, hips, stand)
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
    # nothing to carry slowly where every style the row weighs only clamps the joint: carried whole
    whole = ~np.any((w[:, :, None] != 0.0) & ~clamps_only(other)[None], axis=1)
    out[whole] = carry_by_gait(other, run, q, w, share, hips, stand)[whole]
    return out, new


def clamps_only(carry: StyleCarry) -> np.ndarray:
    """(S, J) bool: the joints `carry` only clamps, per style (its map the identity and its
    source the style's mean: the legs of a clamp-only fit, fixed joints, a joint the carry would
    move off the style's real frames)."""
    eye = np.all(np.abs(carry.map - np.eye(3)) == 0.0, axis=(-1, -2))
    return eye & np.all(carry.source == carry.mean, axis=-1)


def twist_clamp(twists: TwistRange, q: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`twist_stage(twists, q, weights)` in numpy."""
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
    stand: StyleCarry | None = None,
) -> np.ndarray:
    """The compiled `carry_slow` over every frame (T, J, 4) of a clip, each frame's slow copy
    followed in numpy, as a stream sees it."""
    before = np.zeros_like(np.asarray(q, np.float64))  # each frame's slow copy before it
    for t in range(1, len(q)):
        before[t] = follow(before[t - 1 : t], q[t - 1 : t])[0]
    return compiled_carry_slow(other, run, q, before, weights, share, hips, stand)[0]
