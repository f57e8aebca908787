"""The one small streaming interface every method implements and the service calls.

A session's state lives outside the model as a dict of arrays whose first axis is the session,
so one `step_batch` call advances many independent sessions at once (cross-session batching),
and the service can stack, split, snapshot, move and resume any session's state.

Styles are passed per step as a weight vector over `styles()`: a pure style is one-hot, a mix is
several weights, intensity scales the vector (sum < 1 leans toward the unstyled input), and a
style transition is the service interpolating this vector over frames. Each method maps the
vector onto its own mechanism (LTI: blend of per-style outputs; Style-ERD: weighted residual
branches; LPN-FiLM: blended FiLM parameters).
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

    def __len__(self) -> int:
        return self.root.shape[0]

    def take(self, i: int) -> FrameBatch:
        return FrameBatch(self.root[i:i + 1], self.rotations[i:i + 1])

    @staticmethod
    def concat(frames: list[FrameBatch]) -> FrameBatch:
        return FrameBatch(np.concatenate([f.root for f in frames]), np.concatenate([f.rotations for f in frames]))


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


def style_vector(model: StreamingModel, mix: dict[str, float], intensity: float = 1.0) -> np.ndarray:
    """Weights over model.styles() from a {style: weight} mix (normalised to sum 1) times intensity."""
    names = model.styles()
    unknown = sorted(set(mix) - set(names))
    if unknown:
        raise KeyError(f"unknown style(s) {', '.join(unknown)} for model {model.name!r}; known: {', '.join(names)}")
    total = sum(mix.values())
    if total <= 0 or any(w < 0 for w in mix.values()):
        raise ValueError("style weights must be non-negative and not all zero")
    vec = np.zeros(len(names))
    for style, weight in mix.items():
        vec[names.index(style)] = weight / total
    return vec * intensity
