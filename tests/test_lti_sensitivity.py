"""LTI's translated legs move in proportion to a small change of the input's legs.

A real capture's bones carry noise of a degree or so, and another rig's bones sit a few degrees
apart. A translator whose legs multiply such a change many times over turns it into jitter,
pops and sliding feet (the knee's twist DOF barely moves in the training inputs; fitted as given,
its gains into the knee bend reached 37 rad/rad).
"""

from __future__ import annotations

import numpy as np

from models.interface import FrameBatch
from models.lti.model import WEIGHTS_DIR, LTIStyleModel
from models.motion.bn_skeleton import BN_JOINTS, HIPS
from models.motion.rotations import quat_angle, quat_exp, quat_mul
from models.motion.twist import bone_axes

LEGS = ("UpperLeg_L", "LowerLeg_L", "Foot_L", "UpperLeg_R", "LowerLeg_R", "Foot_R")
FRAMES = 240  # 8 s of a walk: several strides of each foot
TWIST_DEG = 1.0


def _walk():
    """The first dataset-2 neutral walk of the validation split."""
    from models.data import build_index, load_motions, select

    clips = [
        c for c in select(build_index(["bandai-namco-2"]), split="val") if c.style == "normal" and c.content == "walk"
    ]
    assert clips, "no dataset-2 validation walk"
    return load_motions(clips[:1])[0].slice(0, FRAMES)


def _twisted(rotations: np.ndarray, joint: int, axis: np.ndarray) -> np.ndarray:
    """`rotations` (F, J, 4) with `joint` turned by TWIST_DEG about its own bone (`axis`)."""
    out = rotations.copy()
    out[:, joint] = quat_mul(out[:, joint], quat_exp(np.radians(TWIST_DEG) * axis))
    return out


def test_a_one_degree_leg_twist_moves_the_translated_legs_about_as_much():
    """The core (systems, erf blend, foot planter) toward elderly on a real walk, with and
    without a 1-degree twist of each leg bone: every output leg joint moves on average no more
    than 1.5 degrees (before the fix: the right shin 4.0, its foot 3.7)."""
    assert (WEIGHTS_DIR / "elderly.npz").exists(), "committed LTI weights missing"
    model = LTIStyleModel(off=("rotation_prior", "hinge_floor", "raised_arm"))
    walk = _walk()
    rotations = walk.rotations.astype(np.float64)
    axes = bone_axes(model.skeleton)
    inputs = [rotations] + [_twisted(rotations, BN_JOINTS.index(j), axes[BN_JOINTS.index(j)]) for j in LEGS]
    B = len(inputs)
    w = np.zeros((B, len(model.styles())))
    w[:, model.styles().index("elderly")] = 1.0
    state, out = model.init_state(B), np.empty((walk.num_frames, B, len(BN_JOINTS), 4))
    root = walk.translations[:, HIPS].astype(np.float64)
    for t in range(walk.num_frames):
        frame = FrameBatch(np.repeat(root[t : t + 1], B, axis=0), np.stack([q[t] for q in inputs]))
        result, state = model.step_batch(state, frame, w)
        out[t] = result.rotations
    legs = [BN_JOINTS.index(j) for j in LEGS]
    moved = np.degrees(quat_angle(out[:, 1:, legs], out[:, :1, legs])).mean(axis=0)  # (twisted input, leg joint)
    worst = np.unravel_index(np.argmax(moved), moved.shape)
    assert moved.max() <= 1.5, f"a 1-degree twist of {LEGS[worst[0]]} moved {LEGS[worst[1]]} {moved.max():.2f} degrees"
