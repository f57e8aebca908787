"""Keep Style-ERD's arm twists inside the twists the real data shows.

A bone's twist about itself moves no joint, yet a skinned arm shows it. Style-ERD's bones take
the input's twists carried by the leaf prior, and then the output prior maps whole rotations
with gains up to 2; each scales a twist with the rest. On the validation clips the p95 of how far
the arms' twist (relative to the style's real mean) went past the real p0.5..p99.5 interval was
13.2 degrees toward masculine (UpperArm_L), 16.4 toward youthful (LowerArm_L) and 9.8 toward
elderly (LowerArm_R), against 0.0 for real clips (both priors add to it). The angle clamps of
the priors bound a rotation's distance from the style's mean, not its twist: a small swing
leaves room for a large twist.

So after the priors each arm joint's twist about its bone, relative to the style's real mean, is
clamped into the style's real TRAIN p1..p99 twist interval (inside the evaluation's p0.5..p99.5,
as the priors' p98 angle clamps sit inside its p99). The swing, which places the joints, is kept:
a twist correction is a rotation about the bone's own axis, applied on the right. Style mixes
blend the corrections by their weights; a row with no style weight is left as it is.
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
