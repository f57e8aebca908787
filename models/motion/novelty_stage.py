"""The unseen-content fade as the last stage of every method's shipped pipeline
(`models/registry.py` adds it to each method with a fitted reference in `weights/novelty/`).

The stage is the method itself with `FadesUnseen` put in front of its class (`with_novelty`), not
a wrapper: the model keeps every ability the service tests with `isinstance` (uploaded styles),
`with_own_styles` copies keep the stage, and the service, crowds, the offline path and the
evaluation all step it through the one `step_batch` they already call. Its state rides in the
session state under `KEYS` (so snapshots, resumes and batching carry it like any other); the
method's own `upgrade_state` never sees those keys, its `step_batch` passes them by. A published
core (`pipeline: core`) is the method alone: the fade is a fitted stage like the others after
the core, and the core is what the method does by itself.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import Any

import numpy as np

from ..interface import FrameBatch, State
from .novelty import ATTACK_FRAMES, FULL_FADE, HEIGHT_WEIGHT, RELEASE_FRAMES, SPEED_WEIGHT, START, NoveltyReference
from .novelty_kernels import fade_step

KEYS = (
    "novelty.w1",
    "novelty.fade",
    "novelty.hint",
    "novelty.prev_in",
    "novelty.prev_model",
    "novelty.offset",
    "novelty.started",
)
_CLASSES: dict[type, type] = {}


def fresh_state(batch: int, parts: int) -> State:
    return {
        "novelty.w1": np.zeros((batch, parts)),
        "novelty.fade": np.zeros((batch, parts)),
        "novelty.hint": np.zeros((batch, parts), np.int64),
        "novelty.prev_in": np.zeros((batch, 3)),
        "novelty.prev_model": np.zeros((batch, 3)),
        "novelty.offset": np.zeros((batch, 3)),
        "novelty.started": np.zeros(batch, bool),
    }


def faded(state: State) -> np.ndarray | None:
    """(B,) how far each session's latest frame was faded toward its input (the largest part's
    weight, 0..1); None for a model without the stage."""
    fade = state.get("novelty.fade")
    return None if fade is None else fade.max(axis=1)


class FadesUnseen:
    """Put in front of a method's class: its output fades toward the input where the input lies
    far from the method's training input (`novelty.py`), per body part, and comes back after."""

    novelty: NoveltyReference

    def init_state(self, batch: int, *args: Any, **kwargs: Any) -> State:
        inner = super().init_state(batch, *args, **kwargs)  # type: ignore[misc]
        return {**inner, **fresh_state(batch, self.novelty.parts)}

    def upgrade_state(self, state: State) -> State:
        inner = {k: v for k, v in state.items() if k not in KEYS}
        upgrade = getattr(super(), "upgrade_state", None)
        upgraded = inner if upgrade is None else upgrade(inner)
        own = {k: state[k] for k in KEYS if k in state}
        if len(own) != len(KEYS) or own["novelty.fade"].shape[1] != self.novelty.parts:
            own = fresh_state(len(next(iter(upgraded.values()))), self.novelty.parts)  # a snapshot from before
        elif upgraded is inner:
            return state
        return {**upgraded, **own}

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        # the whole state: a method may check it against its own `init_state`, which has these keys
        out, new = super().step_batch(state, frames, style_weights)  # type: ignore[misc]
        root = np.ascontiguousarray(frames.root, np.float64)
        posed = np.ones(len(root), bool) if frames.control is None else frames.control[:, 4] <= 0.5
        w1, fade, hint, offset = (
            state[k].copy() for k in ("novelty.w1", "novelty.fade", "novelty.hint", "novelty.offset")
        )
        model_root = np.ascontiguousarray(out.root, np.float64)
        rotations, out_root = np.empty((*np.shape(out.rotations)[:2], 4)), np.empty_like(root)
        knobs = (float(self.fps), HEIGHT_WEIGHT, SPEED_WEIGHT, START, FULL_FADE, ATTACK_FRAMES, RELEASE_FRAMES)  # type: ignore[attr-defined]
        fade_step(
            np.ascontiguousarray(frames.rotations, np.float64), root,
            np.ascontiguousarray(out.rotations, np.float64), model_root, w1, fade, hint,
            state["novelty.prev_in"], state["novelty.prev_model"], offset, state["novelty.started"], posed,
            self.novelty.arrays, knobs, rotations, out_root,
        )  # fmt: skip
        own = {"novelty.w1": w1, "novelty.fade": fade, "novelty.hint": hint, "novelty.offset": offset}
        own |= {"novelty.prev_in": root.copy(), "novelty.prev_model": model_root.copy(), "novelty.started": posed}
        return replace(out, root=out_root, rotations=rotations, faded=fade.max(axis=1)), {**new, **own}


def with_novelty(model: Any, reference: NoveltyReference) -> Any:
    """`model` with the fade as its last stage: an instance of its class with `FadesUnseen` in
    front, holding the same attributes (what `copy.copy` does; the weights are shared)."""
    cls: type = type(model)
    if isinstance(model, FadesUnseen):
        staged_model = copy.copy(model)
    else:
        staged = _CLASSES.get(cls)
        if staged is None:
            staged = _CLASSES[cls] = type(cls.__name__, (FadesUnseen, cls), {"__module__": cls.__module__})
        staged_model = object.__new__(staged)
        staged_model.__dict__.update(model.__dict__)
    staged_model.novelty = reference
    return staged_model
