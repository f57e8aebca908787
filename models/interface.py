"""The one small streaming interface every method implements and the service calls.

A session's state lives outside the model, stacked over sessions, so one `step_batch` call
advances many independent sessions at once (cross-session batching) and the service can
snapshot, move and resume any session's state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np


@dataclass
class FrameBatch:
    """One frame for each of B sessions on the model skeleton (Bandai Namco, 22 joints)."""

    root: np.ndarray  # (B, 3) Hips translation
    rotations: np.ndarray  # (B, J, 4) local joint rotations, scalar-last quaternions

    def __len__(self) -> int:
        return self.root.shape[0]


@runtime_checkable
class StreamingModel(Protocol):
    name: str  # "lti", "erd", "lpn"

    def styles(self) -> list[str]:
        """Target styles a session may ask for."""
        ...

    def init_state(self, style: str, batch: int = 1) -> Any:
        """Fresh state for `batch` sessions that translate into `style`."""
        ...

    def step_batch(self, state: Any, frames: FrameBatch) -> tuple[FrameBatch, Any]:
        """Advance every session by one frame: no look-ahead, constant memory."""
        ...
