"""Whole-clip (offline) Style-ERD: the torch generator over a clip from the learned initial
states, its output turned back into a world-space `Motion` with the same root path, decoding,
rotation priors (`slow_carry.py`, `gait.py`) and foot planting as the streaming model
(runtime.py; the tests check they agree). `foot_lock=False` gives the network's output alone.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from models.motion.rotations import quat_mul, yaw_quat

from ..motion.bn_skeleton import HIPS
from ..motion.feet import model_rig_planter
from ..motion.hinge import Hinges
from ..motion.hinge_floor import HingeFloor
from ..motion.skeleton import Motion
from ..motion.style_carry import StyleCarry
from ..motion.twist import transfer_twist
from .features import BODY, CONTACT, FPS, FeatureMaker, rotate_y
from .gait import clip_smoothed_speed, eased_in, run_share
from .model import Generator
from .slow_carry import clip_carry_slow
from .twist_range import TwistRange


def to_world(
    rot: np.ndarray, root_vel: np.ndarray, height: np.ndarray, yaw: np.ndarray, root0: np.ndarray, fps: float = FPS
) -> tuple[np.ndarray, np.ndarray]:
    """Model outputs of a clip (T,21,4), (T,3), (T,), input yaw (T,), input first root (3,) ->
    Hips translations (T,3) and local rotations (T,22,4)."""
    T = len(rot)
    step = rotate_y(root_vel, yaw) / fps
    step[0] = 0.0
    root = root0[None] + np.cumsum(step, 0)
    root[:, 1] = height
    out = np.zeros((T, 22, 4))
    out[:, 0, 3] = 1.0
    out[:, BODY] = rot
    out[:, 1] = quat_mul(yaw_quat(yaw), rot[:, 0])
    return root, out


@torch.no_grad()
def stylise(
    gen: Generator,
    maker: FeatureMaker,
    motion: Motion,
    weights: np.ndarray,
    style_in: int = -1,
    content: int = -1,
    foot_lock: bool = True,
    leaf_prior: StyleCarry | None = None,
    output_prior: StyleCarry | None = None,
    run_leaf_prior: StyleCarry | None = None,
    run_output_prior: StyleCarry | None = None,
    twist_range: TwistRange | None = None,
    hinges: Hinges | None = None,
    hinge_floor: HingeFloor | None = None,
) -> Motion:
    """The clip stylised with target weights (6,) or per frame (T, 6); the streaming model's
    rotation prior (`leaf_prior`, `output_prior`, and their run versions for the frames the input
    runs in, `gait.py`) where given."""
    root_in = motion.translations[:, 1]
    x, yaw = maker.sequence(root_in, motion.rotations)
    w = torch.as_tensor(np.asarray(weights, dtype=np.float32))
    w = w[None] if w.dim() == 1 else w[None]
    out = gen(torch.as_tensor(x, dtype=torch.float32)[None], torch.tensor([style_in]), torch.tensor([content]), w)
    root, rots = to_world(
        out["rot"][0].double().numpy(),
        out["root_vel"][0].double().numpy(),
        out["height"][0].double().numpy(),
        yaw,
        root_in[0],
    )
    w_frames = np.broadcast_to(np.asarray(weights, np.float64), (len(rots), w.shape[-1]))
    pos = maker.positions(root_in, motion.rotations)
    share = eased_in(run_share(clip_smoothed_speed(pos, FPS)), np.arange(len(pos)))
    source = clip_carry_slow(leaf_prior, run_leaf_prior, motion.rotations, w_frames, share)
    rots = transfer_twist(motion.skeleton, source, rots, hinges=hinges)
    rots = clip_carry_slow(output_prior, run_output_prior, rots, w_frames, share, hips=HIPS)
    if hinge_floor is not None:
        rots = hinge_floor(rots)
    if twist_range is not None:
        rots = twist_range(rots, w_frames)
    if foot_lock:
        root, rots, _ = model_rig_planter(FPS).clip(root, rots, hints=x[:, CONTACT] > 0.5)
    trans = motion.translations.copy()
    trans[:, 1] = root
    return replace(motion, rotations=rots, translations=trans)
