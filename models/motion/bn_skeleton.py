"""The models' skeleton: Bandai Namco's (BN) joints by name, and the indices the kernels need.

Every model runs on this skeleton in this joint order (`assets/bandai_namco.bvh`). numba kernels
read the indices as module-level ints (compile-time constants), so they import them from here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

BN_JOINTS = (  # the trunk and head, the arms, the legs
    ("joint_Root", "Hips", "Spine", "Chest", "Neck", "Head")
    + ("Shoulder_L", "UpperArm_L", "LowerArm_L", "Hand_L", "Shoulder_R", "UpperArm_R", "LowerArm_R", "Hand_R")
    + ("UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L", "UpperLeg_R", "LowerLeg_R", "Foot_R", "Toes_R")
)
NUM_JOINTS = len(BN_JOINTS)
ROOT = BN_JOINTS.index("joint_Root")  # static at the origin, identity rotation
HIPS = BN_JOINTS.index("Hips")  # carries the world translation and heading
BODY = np.array([j for j in range(NUM_JOINTS) if j != ROOT])  # the joints that carry the body (index array)


def missing_joints(names: Sequence[str], wanted: Sequence[str] = BN_JOINTS) -> list[str]:
    """The joints of `wanted` that `names` lack; none: the rig is the model's own (no retargeting)."""
    have = set(names)
    return [n for n in wanted if n not in have]


def body_joints(names: Sequence[str]) -> list[int]:
    """Indices of the joints carrying the body: all but BN's static root."""
    return [j for j, n in enumerate(names) if n != BN_JOINTS[ROOT]]


# BN joint -> its main child: the bone its rotation points (joints not listed are leaves).
PRIMARY_CHILD = {
    "Hips": "Spine",
    "Spine": "Chest",
    "Chest": "Neck",
    "Neck": "Head",
    "Shoulder_L": "UpperArm_L",
    "UpperArm_L": "LowerArm_L",
    "LowerArm_L": "Hand_L",
    "Shoulder_R": "UpperArm_R",
    "UpperArm_R": "LowerArm_R",
    "LowerArm_R": "Hand_R",
    "UpperLeg_L": "LowerLeg_L",
    "LowerLeg_L": "Foot_L",
    "Foot_L": "Toes_L",
    "UpperLeg_R": "LowerLeg_R",
    "LowerLeg_R": "Foot_R",
    "Foot_R": "Toes_R",
}
