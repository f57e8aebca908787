"""Whole-clip (offline) Style-ERD for the trainer's renders: the torch generator over a clip, its
output as a world `Motion` with the streaming model's root path, the input's twists and leaves
and, unless `foot_lock=False`, its feet planted.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from ..motion.rotations import quat_mul, rotate_y, yaw_quat
from ..motion.skeleton import Motion
from ..motion.twist import transfer_twist
from .features import BODY, CONTACT, FPS, FeatureMaker
from .model import Generator
from .runtime import foot_planter


def to_world(
    rot: np.ndarray, root_vel: np.ndarray, height: np.ndarray, yaw: np.ndarray, root0: np.ndarray, fps: float = FPS
) -> tuple[np.ndarray, np.ndarray]:
    """A clip's outputs (T,21,4), (T,3), (T,), input yaw and first root -> Hips translations, rotations."""
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
def network_clip(
    gen: Generator, maker: FeatureMaker, motion: Motion, weights: np.ndarray, style_in: int = -1, content: int = -1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The generator over the clip toward weights (6,) or (T, 6): features, Hips translations, rotations."""
    root_in = motion.translations[:, 1]
    x, yaw = maker.sequence(root_in, motion.rotations)
    w = torch.as_tensor(np.asarray(weights, dtype=np.float32))[None]
    out = gen(torch.as_tensor(x, dtype=torch.float32)[None], torch.tensor([style_in]), torch.tensor([content]), w)
    root, rots = to_world(
        out["rot"][0].double().numpy(),
        out["root_vel"][0].double().numpy(),
        out["height"][0].double().numpy(),
        yaw,
        root_in[0],
    )
    return x, root, rots


def with_root(motion: Motion, x: np.ndarray, root: np.ndarray, rots: np.ndarray, foot_lock: bool = True) -> Motion:
    """`motion` with these Hips translations and rotations, feet planted first where `foot_lock`."""
    if foot_lock:
        root, rots, _ = foot_planter().clip(root, rots, hints=x[:, CONTACT] > 0.5)
    trans = motion.translations.copy()
    trans[:, 1] = root
    return replace(motion, rotations=rots, translations=trans)


def stylise(
    gen: Generator, maker: FeatureMaker, motion: Motion, weights: np.ndarray,
    style_in: int = -1, content: int = -1, foot_lock: bool = True,  # the input's labels (-1: unknown)
) -> Motion:  # fmt: skip
    """The clip stylised by the network with the input's twists and leaves, no stages."""
    x, root, rots = network_clip(gen, maker, motion, weights, style_in, content)
    return with_root(motion, x, root, transfer_twist(motion.skeleton, motion.rotations, rots), foot_lock)
