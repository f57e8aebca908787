"""The unseen-content fade, the pipeline's last stage before the feet are planted
(`models/registry.py` adds it where `weights/novelty/` has a reference): a method steps
`step_unplanted`, then the fade, then `feet.plant_frame`, so a held foot stays put while the fade
turns the leg; one whose `fade_before_feet` is False is faded after its whole step.

The stage is `FadesUnseen` put in front of the method's class (`with_novelty`), not a wrapper, so
`isinstance` checks, `with_own_styles` copies and every `step_batch` caller see the method as it
was. Its state rides in the session state under `KEYS`. A published core (`pipeline: core`) is
the method alone.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..interface import FrameBatch, State
from ..stages import put_in_front, upgrade_with_own
from .feet import plant_frame
from .novelty import NoveltyReference
from .novelty_kernels import FADE, fade_step, state_width

KEY = "novelty.state"  # (B, `state_width`): each session's fade state, one row (`novelty_kernels`)
KEYS = (KEY,)
_NO_CONTROL = np.zeros((0, 5))
_fade_step: Callable[..., None] = fade_step  # mypy reads numba's Dispatcher call as taking fewer arguments


def fresh_state(batch: int, parts: int) -> State:
    return {KEY: np.zeros((batch, state_width(parts)))}


def faded(state: State) -> np.ndarray | None:
    """(B,) how far each session's latest frame was faded (largest part), or None without the stage."""
    own = state.get(KEY)
    if own is None:
        return None
    parts = (own.shape[1] - state_width(0)) // 3
    return own[:, FADE * parts : (FADE + 1) * parts].max(axis=1)


class FadesUnseen:
    """Put in front of a method's class: its output fades toward the input where that is unseen."""

    novelty: NoveltyReference
    novelty_arrays: tuple[np.ndarray, ...]  # `novelty.arrays` at the model's rate

    def init_state(self, batch: int, *args: Any, **kwargs: Any) -> State:
        inner = super().init_state(batch, *args, **kwargs)  # type: ignore[misc]
        return {**inner, **fresh_state(batch, self.novelty.parts)}

    def upgrade_state(self, state: State) -> State:
        parts = self.novelty.parts
        fresh = lambda batch: fresh_state(batch, parts)[KEY]  # noqa: E731
        return upgrade_with_own(state, KEY, state_width(parts), fresh, getattr(super(), "upgrade_state", None))

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        fused = getattr(super(), "step_batch_fading", None)
        if fused is not None:  # the method runs the fade inside its own compiled step
            return fused(state, frames, style_weights, KEY, self.novelty_arrays)
        # a method whose `fade_before_feet` is False plants its feet first (docs/eval/ablation.md)
        before_feet = getattr(super(), "fade_before_feet", True)
        unplanted = getattr(super(), "step_unplanted", None) if before_feet else None
        if unplanted is None:  # a method without planted feet, or that plants them first: the fade is last
            out, new = super().step_batch(state, frames, style_weights)  # type: ignore[misc]
            return self._fade(state, frames, out, new)
        # before the feet are planted: a held foot stays put while the fade turns the leg
        out, new = unplanted(state, frames, style_weights)
        faded_frame, new = self._fade(state, frames, out, new)
        # the planter's entries: from the method's new state where it set them, else as they were
        planted, feet = plant_frame(self.planter, faded_frame, {**state, **new})  # type: ignore[attr-defined]
        return _with_faded(planted, faded_frame.faded), {**new, **feet}

    def _fade(self, state: State, frames: FrameBatch, out: FrameBatch, new: State) -> tuple[FrameBatch, State]:
        """`out` (the method's frame for `frames`) faded toward the input; `new` with the fade's state."""
        control = _NO_CONTROL if frames.control is None else frames.control
        old = state[KEY]
        B = len(old)
        rotations, root, own, fade = (
            np.empty((B, out.rotations.shape[1], 4)),
            np.empty((B, 3)),
            np.empty(old.shape),
            np.empty(B),
        )
        inputs = (frames.rotations, frames.root, out.rotations, out.root, control, old)
        _fade_step(*inputs, self.novelty_arrays, rotations, root, own, fade)
        # built, not `replace`d: at batch 1 dataclasses.replace costs as much as the whole kernel
        staged = FrameBatch(root=root, rotations=rotations, contacts=out.contacts, control=out.control, faded=fade)
        return staged, {**new, KEY: own}


def _with_faded(frame: FrameBatch, faded: np.ndarray | None) -> FrameBatch:
    """`frame` with its `faded` set (built, not `dataclasses.replace`d: see `_fade`)."""
    return FrameBatch(frame.root, frame.rotations, frame.contacts, frame.control, faded)


def with_novelty(model: Any, reference: NoveltyReference) -> Any:
    """`model` with the fade as its last stage (before its feet where `fade_before_feet`)."""
    staged_model = put_in_front(model, FadesUnseen)
    staged_model.novelty = reference
    staged_model.novelty_arrays = reference.arrays(float(model.fps))
    return staged_model
