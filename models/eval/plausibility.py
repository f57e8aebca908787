"""Rotation plausibility: does every joint's local rotation lie where real data of the style puts
it? Positions miss a leaf's rotation and a twist about a bone, which a skinned character shows.

Per body joint, against the style's TRAIN data: the angle to the real mean (within the real p99),
the twist about the bone (p0.5..p99.5), and pops (second difference past the real p99.9). The Hips
is compared without its heading.
"""

from __future__ import annotations

import numpy as np

from ..motion import bn_skeleton
from ..motion.rotations import quat_angle, quat_inv, quat_log, quat_mean, quat_mul, swing_twist, twist_angle
from ..motion.skeleton import Motion, Skeleton
from ..motion.twist import bone_axes

UP = np.array([0.0, 1.0, 0.0])
MAX_FRAMES_PER_STYLE = 60_000  # an even subsample keeps building the reference to seconds


def body_joints(skeleton: Skeleton) -> np.ndarray:
    """Indices of the joints that carry the body (`bn_skeleton.body_joints`)."""
    return np.array(bn_skeleton.body_joints(skeleton.names))


def comparable_rotations(motion: Motion) -> np.ndarray:
    """(F, J, 4) local rotations with the body root's heading (its twist about up) removed."""
    sk = motion.skeleton
    rot = motion.rotations / np.linalg.norm(motion.rotations, axis=-1, keepdims=True)
    root = int(body_joints(sk)[0])
    world, _ = motion.global_transforms()
    out = rot.copy()
    heading = swing_twist(world[:, root], UP)[1]  # the twist about world up, applied last
    out[:, root] = quat_mul(quat_inv(heading), world[:, root])
    return out


def rotation_acceleration(motion: Motion, joints: np.ndarray) -> np.ndarray:
    """(F - 2, len(joints)) degrees: each joint's second difference of comparable rotation."""
    q = comparable_rotations(motion)[:, joints].astype(np.float64)
    turn = quat_log(quat_mul(quat_inv(q[:-1]), q[1:]))
    return np.degrees(np.linalg.norm(np.diff(turn, axis=0), axis=-1))


class RotationReference:
    """Per style and joint, from TRAIN clips: mean, p99 angle, p0.5/p99.5 twist, p99.9 acceleration."""

    def __init__(self, train: dict[str, list[Motion]]):
        sk = next(iter(train.values()))[0].skeleton
        self.joint_index = body_joints(sk)
        self.joints = [sk.names[j] for j in self.joint_index]
        self.axes = bone_axes(sk)[self.joint_index]
        self.styles = list(train)
        self.mean: dict[str, np.ndarray] = {}  # style -> (J, 4)
        self.p99: dict[str, np.ndarray] = {}  # style -> (J,) radians
        self.twist_range: dict[str, np.ndarray] = {}  # style -> (2, J) radians
        self.pop_limit: dict[str, np.ndarray] = {}  # style -> (J,) degrees per frame per frame
        for style, motions in train.items():
            self.pop_limit[style] = np.percentile(
                np.concatenate([rotation_acceleration(m, self.joint_index) for m in motions]), 99.9, axis=0
            )
            q = self.rotations(motions)
            q = q[np.linspace(0, len(q) - 1, min(len(q), MAX_FRAMES_PER_STYLE)).astype(int)]
            self.mean[style] = quat_mean(q, axis=0)
            dist, twist = self.deviation(style, q)
            self.p99[style] = np.percentile(dist, 99, axis=0)
            self.twist_range[style] = np.percentile(twist, [0.5, 99.5], axis=0)

    def rotations(self, motions: list[Motion]) -> np.ndarray:
        """(F, J, 4) comparable rotations of the body joints, all motions' frames."""
        return np.concatenate([comparable_rotations(m)[:, self.joint_index] for m in motions])

    def deviation(self, style: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F, J) angle to the style's mean, and (F, J) signed twist about the bone from it (radians)."""
        mean = self.mean[style]
        return quat_angle(q, mean), twist_angle(quat_mul(quat_inv(mean), q), self.axes)

    def pops(self, style: str, motions: list[Motion]) -> dict:
        """The worst joint's share of frames past the real p99.9 acceleration, which joint, the largest."""
        acc = np.concatenate([rotation_acceleration(m, self.joint_index) for m in motions])
        share = (acc > self.pop_limit[style]).mean(axis=0)
        worst = int(np.argmax(share))
        return {"pops_max": float(share[worst]), "pops_joint": self.joints[worst], "pops_largest_deg": float(acc.max())}

    def plausibility(self, style: str, motions: list[Motion]) -> dict:
        """Per joint: share within the real p99, excess angle and twist, median angle; the worst joints."""
        dist, twist = self.deviation(style, self.rotations(motions))
        beyond = dist - self.p99[style]
        within = (beyond <= 0).mean(axis=0)
        lo, hi = self.twist_range[style]
        twist_out = ((twist < lo) | (twist > hi)).mean(axis=0)
        # degrees past the interval: shins and toes barely twist in real data, so a share alone misleads
        twist_beyond = np.degrees(np.percentile(np.maximum(np.maximum(lo - twist, twist - hi), 0.0), 95, axis=0))
        per_joint = {}
        for k, name in enumerate(self.joints):
            out = beyond[:, k][beyond[:, k] > 0]
            per_joint[name] = {
                "within": float(within[k]),
                "excess_deg": float(np.degrees(np.median(out))) if len(out) else 0.0,
                "twist_outside": float(twist_out[k]),
                "twist_beyond_p95_deg": float(twist_beyond[k]),
                "median_deg": float(np.degrees(np.median(dist[:, k]))),
                "p99_deg": float(np.degrees(self.p99[style][k])),
            }
        worst, worst_twist, farthest = int(np.argmin(within)), int(np.argmax(twist_out)), int(np.argmax(twist_beyond))
        return {
            "min_within": float(within[worst]),
            "worst_joint": self.joints[worst],
            "mean_within": float(within.mean()),
            "max_twist_outside": float(twist_out[worst_twist]),
            "worst_twist_joint": self.joints[worst_twist],
            "max_twist_beyond_deg": float(twist_beyond[farthest]),
            "farthest_twist_joint": self.joints[farthest],
            "per_joint": per_joint,
        }
