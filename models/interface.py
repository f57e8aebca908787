"""The one small streaming interface every method implements and the service calls.

A session's state lives outside the model as a dict of arrays, session axis first, so one
`step_batch` advances many sessions and the service can stack, split, snapshot and move them.

Styles come per step as a weight vector over `styles()` (one-hot, a mix, scaled by intensity;
sum < 1 leans toward the input). The style set may change while sessions run, so the service
keeps each session's `{style: weight}` and builds the vector over the *current* `styles()`
(`weight_vector`). A model whose state depends on its style set also implements
`upgrade_state(state) -> state`: added styles at their initial state, removed ones dropped,
`state` itself when nothing changed; called on every state before a batch is stacked.

Uploaded styles are optional abilities (`UploadedStyles`, `ClipStyles`, checked by `isinstance`);
the service makes every style change on the model-step worker thread, between steps.
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
    # (B, 5) optional control, read by controller models (LPN-FiLM): forward and side velocity (m/s,
    # side + = the character's left) in the desired facing's frame, desired facing yaw (radians about
    # +Y, 0 = facing +Z), gait (0 walk, 1 run), flag (1 = given; 0: follow the input frames)
    control: np.ndarray | None = None
    # (B,) on outputs: the fade toward the input for unseen content (0 = model, 1 = input; `novelty`)
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
        """Advance every session by one frame (no look-ahead, constant memory); `style_weights` (B, S)."""
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
    """{style: weight} as a vector over `names`; a style not among them (deleted) is left out."""
    return np.array([weights.get(style, 0.0) for style in names], dtype=np.float64)


def weight_columns(weights: np.ndarray, names: list[str], to: list[str]) -> np.ndarray:
    """(n, len(names)) weight rows re-indexed over `to`: dropped styles go, new ones weigh 0."""
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
    """A clip that cannot become a style; `unavailable`: the server lacks what it needs, no client error."""

    def __init__(self, code: str, message: str, unavailable: bool = False) -> None:
        super().__init__(message)
        self.code, self.message, self.unavailable = code, message, unavailable


@dataclass
class FineTuned(Generic[S]):
    """A tuning job's result: the style's parameters, or None where the clip's own style was as good."""

    style: S | None
    summary: dict[str, Any]  # figures for the job's record (seconds, held-out metrics, ...)
    message: str  # what the style's record says from now on


class UploadedStyles(StreamingModel, ABC, Generic[S]):
    """A model whose style set changes while sessions run, each upload saved in a folder of its own."""

    @abstractmethod
    def with_own_styles(self) -> Self:
        """This model (weights shared) with a style set of its own."""

    @abstractmethod
    def check_upload(self, frames: int, fine_tune: bool) -> None:
        """Raise `StyleRejected` if a clip of `frames` frames cannot become a style; called before work."""

    @abstractmethod
    def fine_tune_style(self, name: str, clip: Motion, progress: Progress, steps: int) -> FineTuned[S]:
        """A style from `clip`, slowly, on a job thread; `steps` bounds an iterative tune."""

    @abstractmethod
    def install_style(self, name: str, style: S) -> None:
        """Add style `name`; a `ClipStyles` model replaces one of that name, others refuse it."""

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
        """The file a trained style was loaded from (its time is the style's), or None."""
        return None


class ClipStyles(UploadedStyles[S]):
    """Also makes a style from a clip at once, saved as the clip until a tuning job replaces it."""

    clip_style_note: str  # what a style made from its clip is, for the style's record
    tuning_note: str  # what its fine-tuning job does, for the style's record

    @abstractmethod
    def style_from_clip(self, clip: Motion) -> S:
        """A style from `clip` at once (ValueError if unusable), leaving the model as it is."""

    def add_style_from_clip(self, name: str, clip: Motion) -> None:
        self.install_style(name, self.style_from_clip(clip))


def own_style_set(model: StreamingModel) -> StreamingModel:
    """`model` with a style set of its own where it can change (`UploadedStyles`), else as it is."""
    return model.with_own_styles() if isinstance(model, UploadedStyles) else model
