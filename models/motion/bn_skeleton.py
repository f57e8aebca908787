"""The models' skeleton: Bandai Namco's (BN) joints by name, and the indices the kernels need.

Every model (LTI, Style-ERD, LPN-FiLM) runs on this skeleton in this joint order: the committed
asset `assets/bandai_namco.bvh` (`assets.bandai_namco_skeleton`; tests/test_retarget.py checks
that its names are `BN_JOINTS`). Joint indices are derived here from the names; numba kernels
read them as module-level ints (compile-time constants), so they import them from here.
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
    """The joints of `wanted` that a rig's `names` lack, in order. None missing: the rig is taken as
    the model's own (mapped by name, any order, extra joints allowed; no retargeting)."""
    have = set(names)
    return [n for n in wanted if n not in have]


def body_joints(names: Sequence[str]) -> list[int]:
    """Indices of a skeleton's joints that carry the body: all but Bandai Namco's static root
    (a joint of that name, at the origin with the identity rotation, carries nothing); every
    joint of any other rig."""
    return [j for j, n in enumerate(names) if n != BN_JOINTS[ROOT]]


# BN joint -> its main child, along the limb or up the spine: the bone the joint's rotation points
# (the retargeter matches it; joints not listed are leaves).
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
