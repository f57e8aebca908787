"""Rotation prior: every joint's output rotation stays inside the ball that real data of the output
style fills around that joint's mean rotation.

Why: a per-joint LTI system is linear in the exponential map, so a raised arm or a deep knee bend
that lies near the edge of the training data can be carried past anything the style shows (an
elbow bent 15 degrees further than any real elderly take). What a skinned character shows is the
rotation itself, so the output is held to the region real data of the style occupies: per joint,
the angle d to the style's mean rotation is kept as it is up to an inner radius and then saturates
smoothly (tanh) toward an outer radius it never passes:

    d' = d                                                  d <= inner
    d' = inner + (outer - inner) tanh((d - inner) / (outer - inner))   d > inner

along the same geodesic from the mean (the direction of the rotation away from the mean is kept,
only its distance shrinks). The map is continuous with a continuous first derivative, so a
trajectory crossing the inner radius does not kink, and it is the identity inside.

The Hips rotation carries the heading, which is arbitrary: it is compared without its twist about
world up (q = t * c with t the twist of q about +Y, as `models.eval.plausibility` does), so the
prior is the same whatever way the character faces; the twist is put back after clamping.

Radii are quantiles of the real angles (train split, all contents): inner = `inner_q`, outer =
`outer_q` minus a `margin` (see `fit_prior`). The streaming step does the same per joint in
`kernels.py` (`_clamp_joint`); the two agree to round-off (tests).
"""

from __future__ import annotations

import numpy as np

from .representation import HIPS, NUM_JOINTS

NO_PRIOR = np.inf  # radius of a joint (or a style) without a prior: nothing is clamped


def _mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def _inv(q: np.ndarray) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def up_twist(q: np.ndarray) -> np.ndarray:
    """(..., 4) -> the twist of q about world up (+Y), (0, y, 0, w) normalised; identity when q
    has no part about Y (a half turn about a horizontal axis)."""
    t = np.zeros_like(q)
    t[..., 1], t[..., 3] = q[..., 1], q[..., 3]
    n = np.linalg.norm(t, axis=-1, keepdims=True)
    return np.where(n > 1e-12, t / np.maximum(n, 1e-300), np.array([0.0, 0.0, 0.0, 1.0]))


def comparable(rotations: np.ndarray) -> np.ndarray:
    """(..., 22, 4) local rotations -> the same with the Hips' twist about up removed (c in q = t c)."""
    out = np.array(rotations, float, copy=True)
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    h = out[..., HIPS, :]
    out[..., HIPS, :] = _mul(_inv(up_twist(h)), h)
    return out


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0))


def mean_rotation(q: np.ndarray) -> np.ndarray:
    """(N, 4) -> (4,) sign-blind mean (principal eigenvector of sum q q^T), w >= 0."""
    _, vecs = np.linalg.eigh(q.T @ q)
    m = vecs[:, -1]
    return m if m[3] >= 0 else -m


def fit_prior(
    rotations: np.ndarray, inner_q: float = 97.0, outer_q: float = 99.0, margin_deg: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Real frames (F, 22, 4) of one style (all contents) -> (mean (22, 4), radii (2, 22): inner,
    outer, radians). `joint_Root` (static) gets no prior. The outer radius sits `margin_deg`
    inside the real `outer_q` quantile, so an output on it is still within that quantile of real
    frames; the inner radius is the `inner_q` quantile, at most the outer one."""
    c = comparable(rotations)
    mean = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (NUM_JOINTS, 1))
    radii = np.full((2, NUM_JOINTS), NO_PRIOR)
    for j in range(1, NUM_JOINTS):
        mean[j] = mean_rotation(c[:, j])
        d = _angle(c[:, j], mean[j])
        outer = max(np.percentile(d, outer_q) - np.radians(margin_deg), 1e-3)
        radii[:, j] = min(np.percentile(d, inner_q), outer), outer
    return mean, radii


def saturate(d: np.ndarray, inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """The clamped distance d' (see the module docstring); `inner`/`outer` broadcast with d."""
    with np.errstate(invalid="ignore"):  # inf radii (no prior): d stays
        span = np.maximum(outer - inner, 1e-12)
        soft = inner + span * np.tanh((d - inner) / span)
    return np.where(d > inner, np.minimum(soft, outer), d)


def clamp_rotations(rotations: np.ndarray, mean: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(..., 22, 4) local rotations (the Hips with or without its heading) held inside the prior
    (`fit_prior`); a rotation inside the inner radius is returned unchanged."""
    q = np.array(rotations, float, copy=True)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    twist = up_twist(q[..., HIPS, :])
    q[..., HIPS, :] = _mul(_inv(twist), q[..., HIPS, :])
    rel = _mul(_inv(mean), q)  # rotation from the mean, taken with w >= 0 (the short way)
    rel = np.where(rel[..., 3:] < 0, -rel, rel)
    s = np.linalg.norm(rel[..., :3], axis=-1)
    d = 2.0 * np.arctan2(s, rel[..., 3])
    new_d = saturate(d, radii[0], radii[1])
    moved = new_d < d
    axis = rel[..., :3] / np.maximum(s, 1e-300)[..., None]
    half = 0.5 * new_d[..., None]
    clamped = _mul(mean, np.concatenate([axis * np.sin(half), np.cos(half)], axis=-1))
    q = np.where(moved[..., None], clamped, q)
    q[..., HIPS, :] = _mul(twist, q[..., HIPS, :])
    # rotations that were not moved are returned exactly as given (same sign, no round trip)
    return np.where(moved[..., None], q, rotations)
