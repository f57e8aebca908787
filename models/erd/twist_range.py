"""Keep Style-ERD's arm twists inside the twists the real data shows.

A bone's twist moves no joint, yet a skinned arm shows it, and the priors' gains scale twists
with the rest while their angle clamps bound only the distance from the style's mean. So after
the priors each arm joint's twist about its bone, relative to the style's real mean, is clamped
into the style's real TRAIN p1..p99 interval; the swing, which places the joints, is kept.
Style mixes blend the corrections by their weights; a row with no style weight is left alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..motion.rotations import quat_inv, quat_mean, quat_mul, twist_angle
from ..motion.skeleton import Skeleton
from ..motion.twist import bone_axes

TWIST_FILE = "twist_range.npz"
TWIST_JOINTS = ("UpperArm_L", "LowerArm_L", "UpperArm_R", "LowerArm_R")
PERCENTILES = (1.0, 99.0)


@dataclass(frozen=True)
class TwistRange:
    """Per target style and arm joint: the real mean rotation and the twist interval about the bone."""

    joints: np.ndarray  # (K,) joint indices
    axes: np.ndarray  # (K, 3) each joint's bone axis in its own frame
    mean: np.ndarray  # (S, K, 4) the style's real mean local rotation
    lo: np.ndarray  # (S, K) radians
    hi: np.ndarray  # (S, K) radians

    @classmethod
    def fit(cls, skeleton: Skeleton, real: list[np.ndarray]) -> TwistRange:
        """From each target style's real local rotations (N, J, 4)."""
        joints = np.array([skeleton.index(n) for n in TWIST_JOINTS])
        axes = bone_axes(skeleton)[joints]
        mean, lo, hi = [], [], []
        for q in real:
            m = quat_mean(q[:, joints], axis=0)
            t = twist_angle(quat_mul(quat_inv(m)[None], q[:, joints]), axes)
            mean.append(m)
            lo.append(np.percentile(t, PERCENTILES[0], axis=0))
            hi.append(np.percentile(t, PERCENTILES[1], axis=0))
        return cls(joints, axes, np.stack(mean), np.stack(lo), np.stack(hi))

    def save(self, path: Path) -> Path:
        np.savez(path, joints=self.joints, axes=self.axes, mean=self.mean, lo=self.lo, hi=self.hi)
        return path

    @classmethod
    def load(cls, path: Path) -> TwistRange:
        with np.load(path) as z:
            joints = np.ascontiguousarray(z["joints"], np.int64)
            return cls(joints, *(np.ascontiguousarray(z[k], np.float64) for k in ("axes", "mean", "lo", "hi")))

    def __call__(self, q: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(B, J, 4) rotations with each arm joint's twist moved into the styles' real intervals
        by the weights (B, S): t + sum_s w_s (clip(t_s, lo_s, hi_s) - t_s), t_s its twist against
        style s's mean. Compiled (`kernels.twist_clamp_batch`); `tests/reference/erd_carry.py` is the reference."""
        from .kernels import twist_clamp_batch

        q = np.ascontiguousarray(q, np.float64)
        w = np.ascontiguousarray(weights, np.float64)
        return twist_clamp_batch(q, w, self.joints, self.axes, self.mean, self.lo, self.hi, np.empty_like(q))
