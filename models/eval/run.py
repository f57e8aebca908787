"""Streaming clips through a method as the evaluation does: through the streaming interface only,
one batch of sessions per method (all clips x all styles), padded by holding the last frame and
truncated back after."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..data import Clip, build_index, select
from ..interface import FrameBatch, StreamingModel
from ..motion.skeleton import Motion
from .history import with_history

DATASET = "bandai-namco-2"
INPUT_STYLE = "normal"
LOCOMOTION = ("walk", "walk-turn-left", "walk-turn-right", "run")  # what LPN-FiLM, a locomotion controller, is for

GATE_WITHIN = 0.95  # every joint: share of joint-frames within the real style's p99 rotation distance
HISTORY_FRAMES = 300  # running sessions: each clip after 10 s of the clips before it (`history.py`)


def pick_clips(
    per_content: int, contents: tuple[str, ...] | None = None, style: str = INPUT_STYLE, split: str = "test"
) -> list[Clip]:
    clips = select(build_index([DATASET]), split=split, style=style)
    out = []
    for content in sorted({c.content for c in clips}):
        if contents is None or content in contents:
            out += sorted((c for c in clips if c.content == content), key=lambda c: c.name)[:per_content]
    return out


def stylise(
    model: StreamingModel,
    motions: list[Motion],
    targets: list[int],
    chunk: int = 256,
    fades: list[np.ndarray] | None = None,
) -> list[Motion]:
    """Output for motions[i] toward style targets[i] (None: no style); per-clip fades into `fades`."""
    T = max(m.num_frames for m in motions)
    n_styles = len(model.styles())
    out: list[Motion] = []
    for lo in range(0, len(motions), chunk):
        part, tgt = motions[lo : lo + chunk], targets[lo : lo + chunk]
        B = len(part)
        hold = lambda a: np.concatenate([a, np.repeat(a[-1:], T - len(a), 0)])  # noqa: E731
        root = np.stack([hold(m.translations[:, 1]) for m in part]).astype(np.float64)
        rot = np.stack([hold(m.rotations) for m in part]).astype(np.float64)
        weights = np.zeros((B, n_styles))
        for b, k in enumerate(tgt):
            if k is not None:
                weights[b, k] = 1.0
        state = model.init_state(B)
        roots, rots, faded = np.empty_like(root), np.empty_like(rot), np.zeros((B, T))
        for t in range(T):
            frame, state = model.step_batch(state, FrameBatch(root[:, t], rot[:, t]), weights)
            roots[:, t], rots[:, t] = frame.root, frame.rotations
            if frame.faded is not None:
                faded[:, t] = frame.faded
        for b, m in enumerate(part):
            n = m.num_frames
            trans = m.translations.copy()
            trans[:, 1] = roots[b, :n]
            out.append(replace(m, rotations=rots[b, :n], translations=trans))
            if fades is not None:
                fades.append(faded[b, :n])
    return out


def stylise_toward(
    model: StreamingModel | None,
    inputs: list[Motion],
    styles: list[str],
    fades: dict[str, list[np.ndarray]] | None = None,
) -> dict[str, list[Motion]]:
    """Every input toward every style in one batch: style -> outputs (None: the inputs)."""
    if model is None:
        if fades is not None:
            fades.update({s: [np.zeros(m.num_frames) for m in inputs] for s in styles})
        return {s: inputs for s in styles}
    order = [model.styles().index(s) for s in styles]
    flat_fades: list[np.ndarray] = []
    flat = stylise(model, [m for _ in styles for m in inputs], [k for k in order for _ in inputs], fades=flat_fades)
    if fades is not None:
        fades.update({s: flat_fades[i * len(inputs) : (i + 1) * len(inputs)] for i, s in enumerate(styles)})
    return {s: flat[i * len(inputs) : (i + 1) * len(inputs)] for i, s in enumerate(styles)}


def run_after_history(
    model: StreamingModel, inputs: list[Motion], styles: list[str], fades: dict[str, list[np.ndarray]] | None = None
) -> tuple[list[Motion], dict[str, list[Motion]]]:
    """Every input after HISTORY_FRAMES of the others, toward every style; outputs on the scored part."""
    runs = [with_history(inputs, i, HISTORY_FRAMES) for i in range(len(inputs))]
    placed = [whole.slice(start, whole.num_frames) for whole, start in runs]
    whole_fades: dict[str, list[np.ndarray]] = {}
    outs = stylise_toward(model, [whole for whole, _ in runs], styles, whole_fades)
    if fades is not None:
        fades.update({s: [f[start:] for f, (_, start) in zip(whole_fades[s], runs)] for s in styles})
    return placed, {s: [o.slice(start, o.num_frames) for o, (_, start) in zip(outs[s], runs)] for s in styles}
