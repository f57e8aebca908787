"""The one small streaming interface every method implements and the service calls.

A session's state lives outside the model as a dict of arrays whose first axis is the session,
so one `step_batch` call advances many independent sessions at once (cross-session batching),
and the service can stack, split, snapshot, move and resume any session's state.

Styles are passed per step as a weight vector over `styles()`: a pure style is one-hot, a mix is
several weights, intensity scales the vector (sum < 1 leans toward the unstyled input), and a
style transition is the service interpolating this vector over frames. Each method maps the
vector onto its own mechanism (LTI: blend of per-style outputs; Style-ERD: weighted residual
branches; LPN-FiLM: blended FiLM parameters).

A model's style set may change while sessions run (the service adds an uploaded style, or deletes
one, on the live model). So the service keeps each session's style as a `{style: weight}` dict
(`style_weights`) and builds the vector over the *current* `styles()` at every step
(`weight_vector`): a style deleted since simply drops out and its share passes the input through.
A model whose state depends on its style set implements one more, optional, method:

    upgrade_state(state) -> state
        Bring a state made under an older style set to the current one: styles added since get
        their initial state, removed ones are dropped, everything else is kept as it is. Must be
        cheap when nothing changed (return `state` itself). The service calls it on every
        session's state before stacking a batch, so a live session, or one resumed from a
        snapshot, carries on across style changes without interruption.

Use `upgrade_state(model, state)` below to call it on any model.

Styles made from uploaded clips are optional abilities, declared by inheriting the abstract
classes at the end of this module (the service checks `isinstance`, never probes for methods):

    UploadedStyles  a style from a clip by a fine-tuning job; add, remove, save, load and copy
                    (a model with a style set of its own). LTI: a StyleTranslator identified from
                    the clip; LPN-FiLM: a FiLM vector from its fine-tuned generator.
    ClipStyles      also a style from a clip at once (LPN-FiLM: the FiLM generator's embedding of
                    the clip; Style-ERD: the nearest trained branch with stages fitted from the
                    clip), which a fine-tuning job may then replace.

The service calls every style change on the model-step worker thread, between steps.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Protocol, Self, TypeVar, runtime_checkable

import numpy as np

from .motion.skeleton import Motion, Skeleton

State = dict[str, np.ndarray]  # every entry has the session axis first


@dataclass
class FrameBatch:
    """One frame for each of B sessions on the model skeleton (Bandai Namco, 22 joints)."""

    root: np.ndarray  # (B, 3) root (Hips) translation
    rotations: np.ndarray  # (B, J, 4) local joint rotations, scalar-last quaternions
    contacts: np.ndarray | None = None  # (B, 2) left/right foot contact flags, on outputs where a model predicts them
    # (B, 5) optional locomotion control, read by controller models (LPN-FiLM) and ignored by the others:
    # forward and side velocity (m/s, side + = the character's left) in the frame of the desired facing,
    # desired facing yaw (radians about +Y, 0 = facing +Z, as models.motion.features.facing_yaw),
    # gait (0 walk, 1 run), flag (1 = control given; a row with 0 lets the model follow the input frames)
    control: np.ndarray | None = None
    # (B,) on outputs: how far each frame was faded toward its input because the input lay far from
    # the model's training input (0 = the model's own output, 1 = the input; `models.motion.novelty`)
    faded: np.ndarray | None = None

    def __len__(self) -> int:
        return self.root.shape[0]


@runtime_checkable
class StreamingModel(Protocol):
    name: str  # "lti", "erd", "lpn"
    skeleton: Skeleton  # the skeleton frames are expressed on
    fps: float  # the frame rate the model runs at (sessions at other rates are adapted by the service)
    controllable: bool  # a character controller: reads FrameBatch.control (the service's `control` message)

    def styles(self) -> list[str]:
        """Target styles; a style weight vector indexes this list."""
        ...

    def init_state(self, batch: int) -> State:
        """Fresh state for `batch` new sessions."""
        ...

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        """Advance every session by one frame (no look-ahead, constant memory).
        `style_weights` is (B, len(styles())). Returns the stylised frames and the new state."""
        ...


def stack_states(states: list[State]) -> State:
    return {key: np.concatenate([s[key] for s in states]) for key in states[0]}


def upgrade_state(model: StreamingModel, state: State) -> State:
    """`model.upgrade_state(state)` where the model has one (a changeable style set), else `state`."""
    upgrade = getattr(model, "upgrade_state", None)
    return state if upgrade is None else upgrade(state)


def style_weights(model: StreamingModel, mix: dict[str, float], intensity: float = 1.0) -> dict[str, float]:
    """A validated {style: weight} mix over model.styles(), normalised to sum 1, times intensity."""
    names = model.styles()
    unknown = sorted(set(mix) - set(names))
    if unknown:
        raise KeyError(f"unknown style(s) {', '.join(unknown)} for model {model.name!r}; known: {', '.join(names)}")
    if not mix or any(not w >= 0 for w in mix.values()) or max(mix.values()) <= 0:  # `not >=`: NaN too
        raise ValueError("style weights must be non-negative and not all zero")
    peak = max(mix.values())
    if not math.isfinite(peak) or not math.isfinite(intensity):
        raise ValueError("style weights and intensity must be finite")
    scaled = {style: weight / peak for style, weight in mix.items()}  # so a sum near the float limit cannot overflow
    total = sum(scaled.values())
    return {style: weight / total * intensity for style, weight in scaled.items()}


def weight_vector(names: list[str], weights: dict[str, float]) -> np.ndarray:
    """{style: weight} as a vector over `names` (a model's current styles); a style that is not
    among them (deleted since) is left out, so its share passes the input through."""
    return np.array([weights.get(style, 0.0) for style in names], dtype=np.float64)


def weight_columns(weights: np.ndarray, names: list[str], to: list[str]) -> np.ndarray:
    """(n, len(names)) weight rows over styles `names` as rows over `to` (a model's styles now):
    `weight_vector` for many rows at once. A style no longer among them drops out, a new one
    weighs 0."""
    column = {style: i for i, style in enumerate(names)}
    out = np.zeros((len(weights), len(to)))
    for j, style in enumerate(to):
        if style in column:
            out[:, j] = weights[:, column[style]]
    return out


def style_vector(model: StreamingModel, mix: dict[str, float], intensity: float = 1.0) -> np.ndarray:
    """Weights over model.styles() from a {style: weight} mix (normalised to sum 1) times intensity."""
    return weight_vector(model.styles(), style_weights(model, mix, intensity))


# --------------------------------------------------------------------------- optional abilities

# a method's own style parameters, opaque to the service (LTI: a StyleTranslator, LPN-FiLM: a FiLM vector)
S = TypeVar("S")
Progress = Callable[[float, str], None]  # (fraction done, what is happening); it raises to stop the work


class StyleRejected(Exception):
    """A clip, or a request about one, that a model cannot make a style from. `code` names the
    reason in the service's error reply; `unavailable` means the server lacks what it would need
    (training data), not that the client sent something wrong."""

    def __init__(self, code: str, message: str, unavailable: bool = False) -> None:
        super().__init__(message)
        self.code, self.message, self.unavailable = code, message, unavailable


@dataclass
class FineTuned(Generic[S]):
    """What a fine-tuning job produced: the style's parameters, or None where tuning did not
    improve on the style the clip already gives (`ClipStyles`, which then keeps that one)."""

    style: S | None
    summary: dict[str, Any]  # figures for the job's record (seconds, held-out metrics, ...)
    message: str  # what the style's record says from now on


class UploadedStyles(StreamingModel, ABC, Generic[S]):
    """A streaming model whose style set changes while sessions run: styles made from uploaded
    clips are added, deleted ones removed, and each is saved in a folder of its own so that a
    restart, or another replica sharing the folder, loads it again. The service calls
    `install_style` and `remove_style` on the model-step worker thread only."""

    @abstractmethod
    def with_own_styles(self) -> Self:
        """This model (its weights shared, not copied) with a style set of its own: styles added
        to or removed from either leave the other's as it is."""

    @abstractmethod
    def check_upload(self, frames: int, fine_tune: bool) -> None:
        """Raise `StyleRejected` if a clip of `frames` frames (model fps) cannot become a style
        here, with or without a fine-tuning job; called before any work is spent on it."""

    @abstractmethod
    def fine_tune_style(self, name: str, clip: Motion, progress: Progress, steps: int) -> FineTuned[S]:
        """A style named `name` from `clip` (model skeleton, model fps): the slow way, on a job
        thread; the model is not changed. `steps` bounds an iterative fine-tune (LPN-FiLM's
        Adam steps); a closed-form one (LTI's identification) has none and ignores it."""

    @abstractmethod
    def install_style(self, name: str, style: S) -> None:
        """Add style `name` with these parameters. A `ClipStyles` model replaces a style of that
        name (a fine-tuned vector replacing the clip's); others refuse a name they have."""

    @abstractmethod
    def remove_style(self, name: str) -> None:
        """Drop style `name`; sessions that used it carry on with its share passing the input through."""

    @abstractmethod
    def save_style(self, style: S, folder: Path) -> None:
        """Write the style's parameters into `folder` (which exists)."""

    @abstractmethod
    def has_saved_style(self, folder: Path) -> bool:
        """Whether `folder` holds parameters `save_style` wrote."""

    @abstractmethod
    def load_style(self, name: str, folder: Path) -> S:
        """The parameters `save_style` wrote into `folder`, for style `name`."""

    def style_file(self, name: str) -> Path | None:
        """The file a trained style was loaded from (the style's creation time is its time), where
        the method keeps one per style; None otherwise."""
        return None


class ClipStyles(UploadedStyles[S]):
    """Also makes a style from a clip at once, usable as soon as it is added; a fine-tuning job
    may later replace it (`install_style` replaces). Until then nothing but the clip is saved,
    so loading such a style again means making it from the clip again."""

    clip_style_note: str  # what a style made from its clip is, for the style's record
    tuning_note: str  # what its fine-tuning job does, for the style's record

    @abstractmethod
    def style_from_clip(self, clip: Motion) -> S:
        """A style's parameters made from `clip` (model skeleton, model fps) at once; raises
        ValueError for a clip it cannot use. Leaves the model as it is, so it may run on any
        thread beside the model's steps: the service makes it there and only installs it between
        steps (made between steps, an upload's clip held every session's frame up)."""

    def add_style_from_clip(self, name: str, clip: Motion) -> None:
        """Add (or replace) style `name` made from `clip`: `install_style(name, style_from_clip(clip))`."""
        self.install_style(name, self.style_from_clip(clip))


def own_style_set(model: StreamingModel) -> StreamingModel:
    """`model` with a style set of its own where its style set can change (`UploadedStyles`), so
    styles one server adds or removes stay its own; any other model as it is."""
    return model.with_own_styles() if isinstance(model, UploadedStyles) else model
