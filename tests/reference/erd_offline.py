"""Style-ERD's stages over a whole clip in numpy, after the offline network
(`models/erd/offline.py`): the reference the streamed stages are tested against."""

from __future__ import annotations

import numpy as np

from models.erd.features import FPS, FeatureMaker
from models.erd.gait import clip_smoothed_speed, eased_in, run_share
from models.erd.model import Generator
from models.erd.offline import network_clip, with_root
from models.erd.slow_carry import carry_slow, follow
from models.erd.stages import ErdStages
from models.motion.bn_skeleton import HIPS
from models.motion.skeleton import Motion
from models.motion.style_carry import StyleCarry
from models.motion.twist import transfer_twist


def clip_carry_slow(
    other: StyleCarry | None,
    run: StyleCarry | None,
    q: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    hips: int = -1,
) -> np.ndarray:
    """`carry_slow` over every frame (T, J, 4) of a clip, as a stream sees it."""
    before = np.zeros_like(np.asarray(q, np.float64))  # each frame's slow copy before it
    for t in range(1, len(q)):
        before[t] = follow(before[t - 1 : t], q[t - 1 : t])[0]
    return carry_slow(other, run, q, before, weights, share, hips)[0]


def stylise(
    gen: Generator,
    maker: FeatureMaker,
    motion: Motion,
    weights: np.ndarray,
    stages: ErdStages,
    style_in: int = -1,
    content: int = -1,
) -> Motion:
    """The clip stylised as the stream does it (`ErdStages` in its order, each over the whole
    clip): the rotation priors (and their run versions for the frames the input runs in), the
    hinges, their floor, the twist range and the planted feet."""
    s = stages
    x, root, rots = network_clip(gen, maker, motion, weights, style_in, content)
    w_frames = np.broadcast_to(np.asarray(weights, np.float64), (len(rots), np.shape(weights)[-1]))
    pos = maker.positions(motion.translations[:, 1], motion.rotations)
    share = eased_in(run_share(clip_smoothed_speed(pos, FPS)), np.arange(len(pos)))
    source = clip_carry_slow(s.leaf_prior, s.run_leaf_prior, motion.rotations, w_frames, share)
    rots = transfer_twist(motion.skeleton, source, rots, hinges=s.hinges)
    rots = clip_carry_slow(s.output_prior, s.run_output_prior, rots, w_frames, share, hips=HIPS)
    if s.hinge_floor is not None:
        rots = s.hinge_floor(rots)
    if s.twist_range is not None:
        rots = s.twist_range(rots, w_frames)
    return with_root(motion, x, root, rots)
