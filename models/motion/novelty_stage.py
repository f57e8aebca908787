"""The unseen-content fade as the last stage of every method's shipped pipeline
(`models/registry.py` adds it to each method with a fitted reference in `weights/novelty/`).

The stage is the method itself with `FadesUnseen` put in front of its class (`with_novelty`), not
a wrapper: the model keeps every ability the service tests with `isinstance` (uploaded styles),
`with_own_styles` copies keep the stage, and the service, crowds, the offline path and the
evaluation all step it through the one `step_batch` they already call. Its state rides in the
session state under `KEYS` (so snapshots, resumes and batching carry it like any other), and the
method's own `upgrade_state` never sees those keys. A published core (`pipeline: core`) is the
method alone: the fade is a fitted stage like the others after the core.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import Any

import numpy as np

from ..interface import FrameBatch, State
from .bn_skeleton import HIPS
from .novelty import NoveltyReference, blend_rotations, smooth

KEYS = ("novelty.w1", "novelty.fade", "novelty.prev_y", "novelty.started")
_CLASSES: dict[type, type] = {}


def fresh_state(batch: int, parts: int) -> State:
    return {
        "novelty.w1": np.zeros((batch, parts)),
        "novelty.fade": np.zeros((batch, parts)),
        "novelty.prev_y": np.zeros(batch),
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
        inner = {k: v for k, v in state.items() if k not in KEYS}
        out, new = super().step_batch(inner, frames, style_weights)  # type: ignore[misc]
        ref = self.novelty
        root = np.asarray(frames.root, np.float64)
        started = state["novelty.started"]
        speed = np.where(started, (root[:, 1] - state["novelty.prev_y"]) * self.fps / ref.leg, 0.0)  # type: ignore[attr-defined]
        target = ref.target(ref.distances(frames.rotations, np.stack([root[:, 1] / ref.leg, speed], axis=1)))
        if frames.control is not None:  # a controller tick carries no pose: nothing to keep
            target[frames.control[:, 4] > 0.5] = 0.0
        w1, fade = smooth(state["novelty.w1"], state["novelty.fade"], target)
        joint = ref.joint_weights(fade)
        rotations = blend_rotations(np.asarray(out.rotations, np.float64), np.asarray(frames.rotations), joint)
        lower = joint[:, HIPS : HIPS + 1]
        out_root = out.root + lower * (root - out.root) if np.any(lower > 0.0) else out.root
        posed = np.ones(len(root), bool) if frames.control is None else frames.control[:, 4] <= 0.5
        own = {"novelty.w1": w1, "novelty.fade": fade, "novelty.prev_y": root[:, 1].copy(), "novelty.started": posed}
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
