"""`StyleCarry`'s carries in numpy: the references its compiled kernels
(`models/motion/style_carry_kernels.py`) are tested against."""

from __future__ import annotations

import numpy as np

from models.motion.rotations import quat_exp, quat_inv, quat_log, quat_mul
from models.motion.style_carry import StyleCarry


def style(carry: StyleCarry, q: np.ndarray, s: int) -> np.ndarray:
    """f_s(q) for rotations (N, J, 4) toward style s (`style_carry`'s formula)."""
    d = quat_log(quat_mul(quat_inv(carry.source[s])[None], q))
    d = np.einsum("jik,njk->nji", carry.map[s], d)
    norm = np.linalg.norm(d, axis=-1)
    d = d * np.minimum(1.0, carry.radius[s] / np.maximum(norm, 1e-12))[..., None]
    return quat_mul(carry.mean[s][None], quat_exp(d))


def mixed_with(
    carry: StyleCarry, then_b: StyleCarry, then_c: StyleCarry, q: np.ndarray, weights: np.ndarray, share: np.ndarray
) -> np.ndarray:
    """`carry.mixed_with(then_b, then_c, q, weights, share)` in numpy (no Hips heading handling)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w = np.asarray(weights, np.float64)
    r = np.asarray(share, np.float64)[:, None, None]
    correction = np.zeros(q.shape[:-1] + (3,))
    for s in range(w.shape[1]):
        ws = w[:, s][:, None, None]
        a = np.stack([style(carry, q[i : i + 1], s)[0] for i in range(len(q))])
        bc = np.stack([style(then_c, style(then_b, q[i : i + 1], s), s)[0] for i in range(len(q))])
        inv = quat_inv(q)
        correction += ws * ((1 - r) * quat_log(quat_mul(inv, a)) + r * quat_log(quat_mul(inv, bc)))
    return quat_mul(q, quat_exp(correction))
