"""The shape every method shares: its published core, then a declared pipeline of general stages.

A stage changes a frame's local rotations after the core. It is fitted from real clips the same
way for every style and reads per style only the rows that fit gave it; a style it was not fitted
for (an upload) gets a row that leaves the frame as it is. A method declares its stages in order
(`StageSpec`); `Pipeline` loads, runs and switches them off (`without`), the same for the
streaming step and the offline path.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from .interface import State
from .motion.skeleton import Skeleton

Rows = Mapping[str, np.ndarray]


class StageFrame(NamedTuple):
    """One frame of B sessions as a stage sees it."""

    rotations: np.ndarray  # (B, J, 4) local rotations from the core or the stage before
    weights: np.ndarray  # (B, S) style weights over the model's styles
    gait: np.ndarray  # (B,) -1 standing, 0 walking, 1 running (linear between)
    base: int  # the style the weights' shortfall from 1 goes to


@runtime_checkable
class Stage(Protocol):
    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """The arrays the step reads, per style aligned with `styles` (unfitted: a no-op row)."""
        ...

    def init_state(self, batch: int) -> State:
        """What the stage keeps per session between frames (keys without the session axis)."""
        ...

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        """The frame's new rotations (same shape and dtype) and the new state."""
        ...

    def save(self, path: Path) -> Path:
        """The fitted stage into its file (`StageSpec.load` reads it back)."""
        ...


def style_rows(
    fitted: Sequence[str], styles: Sequence[str | None], **arrays: tuple[np.ndarray, np.ndarray | float]
) -> dict[str, np.ndarray]:
    """`Stage.rows` from arrays fitted for `fitted` styles, aligned with `styles`."""
    at = [fitted.index(s) if s in fitted else None for s in styles]
    return {k: np.stack([plain if i is None else values[i] for i in at]) for k, (values, plain) in arrays.items()}


class Stateless:
    def init_state(self, batch: int) -> State:
        return {}


@dataclass(frozen=True)
class StageSpec:
    """One declared stage: name (the switch), file, reader, and `fit(model, styles)`."""

    name: str
    file: str
    load: Callable[[Path, Skeleton], Stage]
    fit: Callable[[Any, list[str] | None], Stage]


def refit(spec: StageSpec, model: Any, folder: Path, styles: list[str] | None) -> Path:
    """Fit `spec` for `styles` (None: all) into `folder`, keeping other styles where it can."""
    path = folder / spec.file
    stage = spec.fit(model, styles)
    if styles and path.exists() and hasattr(stage, "with_styles_of"):
        stage = spec.load(path, model.skeleton).with_styles_of(stage)  # type: ignore[attr-defined]
    return stage.save(path)


@dataclass(frozen=True)
class Pipeline:
    """A method's declared stages in the order they run; a stage left None is off."""

    stages: tuple[tuple[str, Stage | None], ...] = ()
    _on: tuple[tuple[str, Stage, tuple[tuple[str, str], ...]], ...] = field(init=False, repr=False, compare=False)
    # the session state these stages keep: key ("stage/name") -> (shape without the session axis, dtype)
    state_layout: dict[str, tuple[tuple[int, ...], np.dtype]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # per stage that is on: its name and its state's keys, with and without the name
        states = {k: s.init_state(0) for k, s in self.stages if s is not None}
        on = tuple((k, s, tuple((f"{k}/{key}", key) for key in states[k])) for k, s in self.stages if s is not None)
        object.__setattr__(self, "_on", on)
        layout = {f"{k}/{key}": (v.shape[1:], v.dtype) for k, state in states.items() for key, v in state.items()}
        object.__setattr__(self, "state_layout", layout)

    @classmethod
    def load(cls, specs: Sequence[StageSpec], folder: Path, skeleton: Skeleton, core_only: bool = False) -> Pipeline:
        """The stages fitted in `folder` (a missing file: off); `core_only`: all off."""
        on = lambda s: not core_only and (folder / s.file).exists()  # noqa: E731
        return cls(tuple((s.name, s.load(folder / s.file, skeleton) if on(s) else None) for s in specs))

    def __getattr__(self, name: str) -> Stage | None:
        for key, stage in self.__dict__.get("stages", ()):  # not `self.stages`: unpickling asks first
            if key == name:
                return stage
        raise AttributeError(f"no stage {name!r}: the pipeline declares {[k for k, _ in self.stages]}")

    def replace(self, **stages: Stage | None) -> Pipeline:
        """These stages replaced (None: off), the rest as they are."""
        unknown = set(stages) - {k for k, _ in self.stages}
        if unknown:
            raise KeyError(f"undeclared stages {sorted(unknown)}")
        return Pipeline(tuple((k, stages.get(k, s)) for k, s in self.stages))

    def without(self, *names: str) -> Pipeline:
        return self.replace(**dict.fromkeys(names))

    def split(self, last: str) -> tuple[Pipeline, Pipeline]:
        """The stages up to `last` and those after (Style-ERD's core reads the first ones' output)."""
        at = [k for k, _ in self.stages].index(last) + 1
        return Pipeline(self.stages[:at]), Pipeline(self.stages[at:])

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, dict[str, np.ndarray]]:
        return {k: s.rows(styles, skeleton) for k, s in self.stages if s is not None}

    def init_state(self, batch: int) -> State:
        return {f"{k}/{key}": v for k, s, _ in self._on for key, v in s.init_state(batch).items()}

    def step_batch(
        self, state: State, frame: StageFrame, rows: Mapping[str, Rows]
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The frame through every stage that is on; `rows`: `self.rows(...)` for the frame's styles."""
        out: dict[str, np.ndarray] = {}
        rotations, weights, gait, base = frame
        for k, s, keys in self._on:
            rotations, own = s.step_batch({key: state[full] for full, key in keys}, frame, rows[k])
            frame = StageFrame(rotations, weights, gait, base)  # not `_replace`: ~1 us a call
            for full, key in keys:
                out[full] = own[key]
        return rotations, out


_IN_FRONT: dict[tuple[type, type], type] = {}


def upgrade_with_own(
    state: State, key: str, width: int, fresh: Callable[[int], np.ndarray], upgrade: Callable[[State], State] | None
) -> State:
    """A front stage's `upgrade_state`: the method's entries upgraded, its own row kept or fresh."""
    inner = {k: v for k, v in state.items() if k != key}
    upgraded = inner if upgrade is None else upgrade(inner)
    own = state.get(key)
    if own is None or own.shape[1] != width:
        own = fresh(len(next(iter(upgraded.values()))))
    elif upgraded is inner:
        return state
    return {**upgraded, key: own}


def put_in_front(model: Any, mixin: type) -> Any:
    """A copy of `model` whose class has `mixin` in front (one class per pair, cached): a stage that
    wraps the whole step without wrapping the object, so `isinstance`, `with_own_styles` and every
    `step_batch` caller see the method as it was. The copy shares the model's weights."""
    cls: type = type(model)
    if isinstance(model, mixin):
        return copy.copy(model)
    staged = _IN_FRONT.get((cls, mixin))
    if staged is None:
        staged = _IN_FRONT[(cls, mixin)] = type(cls.__name__, (mixin, cls), {"__module__": cls.__module__})
    out: Any = object.__new__(staged)
    out.__dict__.update(model.__dict__)
    return out
