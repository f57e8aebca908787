"""`coupling.couple` in numpy: the reference its compiled kernels
(`models/motion/coupling_kernels.py`) are tested against."""

from __future__ import annotations

import numpy as np

from models.motion.coupling import _coupled, moved
from models.motion.rotations import quat_exp, quat_inv, quat_log, quat_mul


def couple_numpy(
    rotations: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    joints: tuple[np.ndarray, np.ndarray],
    aligned: dict[str, np.ndarray],
) -> np.ndarray:
    """`coupling.couple`, a link and a style at a time."""
    rows, w = _coupled(weights, aligned["on"])
    if len(rows) == 0:
        return rotations
    w, r = w[rows], np.clip(np.asarray(share, np.float64)[rows], 0.0, 1.0)[:, None, None]
    q = np.asarray(rotations[rows], np.float64)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    for k, (t, ds) in enumerate(zip(*joints)):
        correction = np.zeros((len(rows), 3))
        for s in np.flatnonzero(w.any(axis=0)):
            walk, run = aligned["walk"][s, k], aligned["run"][s, k]
            styled = moved(q, aligned["mean"][s], t, ds, walk + r * (run - walk))
            correction += w[:, s, None] * quat_log(quat_mul(quat_inv(q[:, t]), styled))
        q[:, t] = quat_mul(q[:, t], quat_exp(correction))
    out = np.array(rotations, copy=True)
    out[np.ix_(rows, joints[0])] = q[:, joints[0]]
    return out
