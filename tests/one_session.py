"""Helpers for tests that stream validation clips through one session of a model, frame by frame,
as a client does."""

from __future__ import annotations

import numpy as np

from models.interface import FrameBatch
from models.motion.bn_skeleton import HIPS


def val_motions(index, content: str, style: str = "normal", n: int = 1, frames: int = 150) -> list:
    """The first `n` Bandai Namco dataset-2 VALIDATION clips of `style` and `content`, cut to `frames`."""
    from models.data import load_motions, select

    clips = select(index, dataset="bandai-namco-2", split="val", style=style, content=content)[:n]
    return [m.slice(0, frames) for m in load_motions(clips)]


def stream(model, motion, style: str) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 4) rotations and (T, 3) roots of `motion` streamed frame by frame toward `style`."""
    w = np.zeros((1, len(model.styles())))
    w[0, model.styles().index(style)] = 1.0
    state, rots, roots = model.init_state(1), [], []
    for t in range(motion.num_frames):
        frame = FrameBatch(motion.translations[t : t + 1, HIPS], motion.rotations[t : t + 1])
        out, state = model.step_batch(state, frame, w)
        rots.append(out.rotations[0])
        roots.append(out.root[0])
    return np.array(rots), np.array(roots)


def assert_lti_streams_as_offline(model, motion, style: str) -> None:
    """An `LTIStyleModel`'s stream, frame by frame, equals its translator's offline
    numpy reference of the whole clip (`reference/lti_offline.py`: the same carries, in the same order)."""
    from .reference.lti_offline import offline

    offline, _ = offline(model, style, motion)
    rots, roots = stream(model, motion, style)
    np.testing.assert_allclose(roots, offline.translations[:, HIPS], atol=1e-8)
    np.testing.assert_allclose(rots, offline.rotations, atol=1e-10)


def contents_read(models, inputs: list, style: str) -> list[list[str]]:
    """Per model, what the content judge reads in each of `inputs` streamed toward `style`
    (fresh sessions, as `make eval` scores them)."""
    from models.eval.features import clip_features
    from models.eval.judges import load_judges
    from models.eval.run import stylise

    judges = load_judges()
    read = []
    for model in models:
        outputs = stylise(model, inputs, [model.styles().index(style)] * len(inputs))
        read.append(judges.predict_content([clip_features(o) for o in outputs]))
    return read
