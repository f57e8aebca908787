"""The pipelines a session may ask for: a method's shipped pipeline (`full`, its published core
followed by its fitted stages) or its published core alone (`core`).

Inside the server each pipeline is a model of its own under a key: the method's name for the
full pipeline, `<name>:core` for the core. Batchers, session counts, crowd troupes and metrics
all go by that key, so sessions of the two pipelines of one method never share a batch or a
state, while the core sessions of one method batch together. On the wire and in snapshots the
key is split back into `model` and `pipeline` (`split`): an old snapshot without a pipeline
is a full one.

The core's style set is the method's built-in styles and never changes: an uploaded style is
made for the full pipeline (the store fits its stages), so asking the core for one is the typed
error `style_not_in_pipeline`, not a silent fallback.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from models.interface import FrameBatch, State, StreamingModel, upgrade_state
from models.motion.skeleton import Skeleton

Pipeline = Literal["full", "core"]
PIPELINES: tuple[Pipeline, ...] = ("full", "core")
CORE_SUFFIX = ":core"


def key(model: str, pipeline: str = "full") -> str:
    """The server's name for `model`'s `pipeline`: "lti" (full), "lti:core"."""
    return model if pipeline == "full" else model + CORE_SUFFIX


def split(name: str) -> tuple[str, Pipeline]:
    """`key`'s inverse: (model, pipeline)."""
    if name.endswith(CORE_SUFFIX):
        return name[: -len(CORE_SUFFIX)], "core"
    return name, "full"


class CorePipeline:
    """A method's published core (`load(..., core_only=True)`) under its own key, so that the
    server tells it from the full pipeline of the same method everywhere it goes by name."""

    def __init__(self, core: StreamingModel) -> None:
        self.core = core
        self.name: str = key(core.name, "core")
        self.skeleton: Skeleton = core.skeleton
        self.fps: float = core.fps
        self.controllable: bool = core.controllable

    def styles(self) -> list[str]:
        return self.core.styles()

    def init_state(self, batch: int) -> State:
        return self.core.init_state(batch)

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        return self.core.step_batch(state, frames, style_weights)

    def upgrade_state(self, state: State) -> State:
        return upgrade_state(self.core, state)


def core_pipelines(cores: dict[str, StreamingModel]) -> dict[str, StreamingModel]:
    """`{model: core}` (`load_models(..., core_only=True)`) as `{key: pipeline}`."""
    return {key(name, "core"): CorePipeline(core) for name, core in cores.items()}
