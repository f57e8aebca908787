"""Keep Style-ERD's arm twists inside the twists the real data shows.

A twist moves no joint, yet a skinned arm shows it, and the priors' clamps bound only the distance
from the mean. So after the priors each arm joint's twist relative to the style's mean is clamped
into its real TRAIN p1..p99 interval, blended by the style weights; the swing is kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..interface import State
from ..motion.rotations import quat_inv, quat_mean, quat_mul, twist_angle
from ..motion.skeleton import Skeleton
from ..motion.twist import bone_axes
from ..stages import Rows, StageFrame, Stateless, style_rows
from .dataset import STYLES, TARGET_STYLES

TWIST_FILE = "twist_range.npz"
TWIST_JOINTS = ("UpperArm_L", "LowerArm_L", "UpperArm_R", "LowerArm_R")
PERCENTILES = (1.0, 99.0)


@dataclass(frozen=True)
class TwistRange(Stateless):
    """The stage: per fitted style and arm joint, the real mean rotation and twist interval."""

    joints: np.ndarray  # (K,) joint indices
    axes: np.ndarray  # (K, 3) each joint's bone axis in its own frame
    mean: np.ndarray  # (S, K, 4) the style's real mean local rotation
    lo: np.ndarray  # (S, K) radians
    hi: np.ndarray  # (S, K) radians
    styles: tuple[str, ...] = TARGET_STYLES

    @classmethod
    def fit(cls, skeleton: Skeleton, real: list[np.ndarray], styles: Sequence[str] = TARGET_STYLES) -> TwistRange:
        """From each of `styles`' real local rotations (N, J, 4)."""
        joints = np.array([skeleton.index(n) for n in TWIST_JOINTS])
        axes = bone_axes(skeleton)[joints]
        mean, lo, hi = [], [], []
        for q in real:
            m = quat_mean(q[:, joints], axis=0)
            t = twist_angle(quat_mul(quat_inv(m)[None], q[:, joints]), axes)
            mean.append(m)
            lo.append(np.percentile(t, PERCENTILES[0], axis=0))
            hi.append(np.percentile(t, PERCENTILES[1], axis=0))
        return cls(joints, axes, np.stack(mean), np.stack(lo), np.stack(hi), tuple(styles))

    def save(self, path: Path) -> Path:
        np.savez(path, joints=self.joints, axes=self.axes, mean=self.mean, lo=self.lo, hi=self.hi)
        return path

    @classmethod
    def load(cls, path: Path) -> TwistRange:
        with np.load(path) as z:
            axes, mean, lo, hi = (np.ascontiguousarray(z[k], np.float64) for k in ("axes", "mean", "lo", "hi"))
            return cls(np.ascontiguousarray(z["joints"], np.int64), axes, mean, lo, hi)

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """The styles' means and intervals; a style not fitted gets an unbounded one."""
        identity = np.tile((0.0, 0.0, 0.0, 1.0), (len(self.joints), 1))
        return style_rows(self.styles, styles, mean=(self.mean, identity), lo=(self.lo, -np.inf), hi=(self.hi, np.inf))

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        """Arm twists moved into the styles' intervals by the weights (`kernels.twist_clamp_batch`)."""
        from .kernels import twist_clamp_batch

        q = np.ascontiguousarray(frame.rotations, np.float64)
        w = np.ascontiguousarray(frame.weights, np.float64)
        out = twist_clamp_batch(q, w, self.joints, self.axes, rows["mean"], rows["lo"], rows["hi"], np.empty_like(q))
        return out, state

    def stacked(self, others: Sequence[tuple[str, TwistRange]]) -> TwistRange:
        """This range with each of `others` (name, one style's range) as one more style."""
        return replace(
            self,
            mean=np.concatenate([self.mean, *(o.mean for _, o in others)]),
            lo=np.concatenate([self.lo, *(o.lo for _, o in others)]),
            hi=np.concatenate([self.hi, *(o.hi for _, o in others)]),
            styles=self.styles + tuple(n for n, _ in others),
        )

    def with_styles_of(self, other: TwistRange) -> TwistRange:
        at = [self.styles.index(s) for s in other.styles]
        mean, lo, hi = self.mean.copy(), self.lo.copy(), self.hi.copy()
        mean[at], lo[at], hi[at] = other.mean, other.lo, other.hi
        return replace(self, mean=mean, lo=lo, hi=hi)


def fit(model: Any, styles: list[str] | None = None) -> TwistRange:
    """The range of `styles` (default: every target style) from their real TRAIN frames."""
    from .rotation_prior import real_rotations

    styles = styles or list(TARGET_STYLES)
    real = real_rotations()
    return TwistRange.fit(model.skeleton, [real[STYLES.index(s)] for s in styles], styles)
