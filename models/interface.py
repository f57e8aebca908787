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
A model whose style set can change implements one more, optional, method:

    upgrade_state(state) -> state
        Bring a state made under an older style set to the current one: styles added since get
        their initial state, removed ones are dropped, everything else is kept as it is. Must be
        cheap when nothing changed (return `state` itself). The service calls it on every
        session's state before stacking a batch, so a live session, or one resumed from a
        snapshot, carries on across style changes without interruption.

(The LTI model also has `add_style(translator)` / `remove_style(name)`; the service calls them on
the model-step worker thread, between steps.) Use `upgrade_state(model, state)` below to call it
on any model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from .motion.skeleton import Skeleton

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

    def __len__(self) -> int:
        return self.root.shape[0]

    def take(self, i: int) -> FrameBatch:
        control = None if self.control is None else self.control[i:i + 1]
        return FrameBatch(self.root[i:i + 1], self.rotations[i:i + 1], control=control)

    @staticmethod
    def concat(frames: list[FrameBatch]) -> FrameBatch:
        """Frames of many sessions as one batch; rows without control get a zero (not given) control row."""
        control = None
        if any(f.control is not None for f in frames):
            control = np.concatenate([f.control if f.control is not None else np.zeros((len(f), 5)) for f in frames])
        return FrameBatch(np.concatenate([f.root for f in frames]), np.concatenate([f.rotations for f in frames]),
                          control=control)


@runtime_checkable
class StreamingModel(Protocol):
    name: str  # "lti", "erd", "lpn"
    skeleton: Skeleton  # the skeleton frames are expressed on
    fps: float  # the frame rate the model runs at (sessions at other rates are adapted by the service)

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


def split_state(state: State) -> list[State]:
    n = len(next(iter(state.values())))
    return [{key: value[i:i + 1] for key, value in state.items()} for i in range(n)]


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
    total = sum(mix.values())
    if total <= 0 or any(w < 0 for w in mix.values()):
        raise ValueError("style weights must be non-negative and not all zero")
    return {style: weight / total * intensity for style, weight in mix.items()}


def weight_vector(names: list[str], weights: dict[str, float]) -> np.ndarray:
    """{style: weight} as a vector over `names` (a model's current styles); a style that is not
    among them (deleted since) is left out, so its share passes the input through."""
    return np.array([weights.get(style, 0.0) for style in names], dtype=np.float64)


def style_vector(model: StreamingModel, mix: dict[str, float], intensity: float = 1.0) -> np.ndarray:
    """Weights over model.styles() from a {style: weight} mix (normalised to sum 1) times intensity."""
    return weight_vector(model.styles(), style_weights(model, mix, intensity))
