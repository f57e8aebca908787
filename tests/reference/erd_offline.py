"""Whole-clip Style-ERD with its stages run frame by frame as the stream runs them: the reference
the stream (`tests.clips.stylise_stream`) and `models.erd.distill.teacher_rotations` (all styles as
one batch) are tested against."""

from __future__ import annotations

import numpy as np

from models.erd.features import FPS
from models.erd.gait import clip_gait
from models.erd.offline import network_clip, with_root
from models.motion.skeleton import Motion


def stylise(
    gen, model, motion: Motion, weights: np.ndarray, style_in: int = -1, content: int = -1, foot_lock: bool = True
) -> Motion:
    """The clip stylised by `model`'s generator `gen` toward target weights (6,) or per frame
    (T, 6), then decoded and staged frame by frame as `model`'s stream does
    (`ERDModel.stage_batch`), the gait shares measured over the clip (`gait.clip_gait`)."""
    x, root, rots = network_clip(gen, model.maker, motion, weights, style_in, content)
    T = len(rots)
    w = np.broadcast_to(np.asarray(weights, np.float64), (T, np.shape(weights)[-1]))
    pos = model.maker.positions(motion.translations[:, 1], motion.rotations)
    share = clip_gait(pos, FPS)
    state = model.stages.init_state(1)
    for t in range(T):
        frame = slice(t, t + 1)
        out, state = model.stage_batch(state, motion.rotations[frame], rots[frame], w[frame], share[frame])
        rots[t] = out[0]
    return with_root(motion, x, root, rots, foot_lock)
