"""Causal per-frame Style-ERD features, one code path for the offline cache and the live stream.

Per frame of the Bandai Namco skeleton (22 joints, `joint_Root` static at 0, `Hips` at 1):

  [0:84)     local rotations (xyzw) of joints 1..21, the Hips without its facing yaw, each in the
             hemisphere of its reference (the data's mean): continuous without other frames
  [84:147)   joint positions in the facing frame (origin = Hips projected on the ground)
  [147:210)  joint velocities (world, backward difference) expressed in the facing frame, cm/s
  [210:213)  root (Hips) velocity in the facing frame, cm/s
  [213]      yaw rate, rad/s
  [214:216)  foot contacts (left, right) as 0/1

Frame t uses frames t and t-1 only, as `models.motion.features.compute_features`.
"""

from __future__ import annotations

import numpy as np

from ..motion.bn_skeleton import BODY
from ..motion.features import body_joint, facing_yaw, left_leg_length
from ..motion.kinematics_kernels import forward_kinematics
from ..motion.skeleton import Skeleton
from . import kernels

NB = len(BODY)  # 21
ROT = slice(0, 4 * NB)
POS = slice(4 * NB, 7 * NB)
VEL = slice(7 * NB, 10 * NB)
ROOTVEL = slice(10 * NB, 10 * NB + 3)
YAWRATE = 10 * NB + 3
CONTACT = slice(10 * NB + 4, 10 * NB + 6)
FEATURE_DIM = 10 * NB + 6  # 216
FPS = 30.0


class FeatureMaker:
    """Causal features for a batch of streams, or all frames of one clip, by compiled kernels."""

    def __init__(self, skeleton: Skeleton, ref: np.ndarray, fps: float = FPS):
        self.sk = skeleton
        self.ref = np.ascontiguousarray(np.asarray(ref, dtype=np.float64)[BODY])
        self.fps = float(fps)
        self.parents = np.asarray(skeleton.parents, dtype=np.int64)
        self.offsets = np.ascontiguousarray(skeleton.offsets, dtype=np.float64)
        self.leg = left_leg_length(skeleton)
        self.facing = np.array(
            [body_joint(skeleton, p) for p in ("hip_l", "hip_r", "shoulder_l", "shoulder_r")], np.int64
        )
        self.feet = np.array(
            [(body_joint(skeleton, f"ankle_{s}"), body_joint(skeleton, f"toe_{s}")) for s in ("l", "r")], np.int64
        )

    def positions(self, root: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """World joint positions (N, 22, 3) from Hips translations (N, 3) and local rotations (N, 22, 4)."""
        return forward_kinematics(_f64(root), _f64(rotations), self.parents, self.offsets)[1]

    def features(
        self, rotations: np.ndarray, pos: np.ndarray, prev_pos: np.ndarray, prev_yaw: np.ndarray, has_prev: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(N, 216) features and (N,) yaw given each frame's previous positions/yaw (where has_prev)."""
        return kernels.features(
            _f64(rotations),
            _f64(pos),
            _f64(prev_pos),
            _f64(prev_yaw),
            np.ascontiguousarray(has_prev, dtype=np.bool_),
            self.ref,
            self.facing,
            self.feet,
            self.leg,
            self.fps,
        )

    def sequence(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features (F, 216) and yaw (F,) of one clip, every frame causal (frame 0 has no past)."""
        pos = self.positions(root, rotations)
        yaw = facing_yaw(pos, self.sk)
        prev_pos = np.concatenate([pos[:1], pos[:-1]])
        prev_yaw = np.concatenate([yaw[:1], yaw[:-1]])
        has_prev = np.arange(len(pos)) > 0
        return self.features(rotations, pos, prev_pos, prev_yaw, has_prev)


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)
