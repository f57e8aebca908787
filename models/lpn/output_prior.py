"""LPN-FiLM's output prior: the body's rotations carried from what the network makes toward a
style to that style's real rotations (`python -m models.lpn fit --stages output_prior` writes
`OUTPUT_PRIOR_FILE`; the same fit for every style).

The carriage moves each joint's mean; a style also lies in how the arms and spine swing about it.
As Style-ERD's prior (`models/motion/style_carry.py`): a Gaussian optimal-transport map, clamped
into the real p98 radius; walks and runs apart, mixed by gait share. The network's spread is
floored at `SOURCE_FLOOR_DEG`, else near-still axes get huge gains.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..eval.run import DATASET, INPUT_STYLE
from ..interface import State
from ..motion.coupling import GAITS
from ..motion.skeleton import Skeleton
from ..motion.style_carry import FIELDS, StyleCarry, carry_rows
from ..stages import Rows, StageFrame, Stateless, style_rows
from .carriage import UPPER_BODY, fitted_styles, locomotion, made

if TYPE_CHECKING:
    from .runtime import LPNModel

OUTPUT_PRIOR_FILE = "output_prior.npz"
CARRIED = UPPER_BODY  # the joints every style's prior carries (module doc)
SOURCE_FLOOR_DEG = 4.0  # the network's least spread along any axis, as the fit takes it (module doc)
FIT_FRAMES = 300


@dataclass(frozen=True)
class OutputPrior(Stateless):
    """The stage: per fitted style, the walking carry's rows and the running one's."""

    styles: tuple[str, ...]
    carry: StyleCarry
    run: StyleCarry

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """The walk and run carries' arrays (`run_` prefixed) and `on` (S,), aligned with `styles`."""
        arrays = carry_rows({"": self.carry, "run_": self.run}, skeleton.num_joints)
        return style_rows(self.styles, styles, on=(np.ones(len(self.styles)), 0.0), **arrays)

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        """Rows weighing a style with a prior carried, walk and run by gait share; others as they were."""
        rotations = frame.rotations
        w = np.asarray(frame.weights, np.float64) * rows["on"][None]
        batch = np.flatnonzero(w.any(axis=1))
        if len(batch) == 0:
            return rotations, state
        walk = StyleCarry(*(rows[k] for k in FIELDS))
        q, w = np.asarray(rotations[batch], np.float64), w[batch]
        # a run share only where a row weighs a style with its own run prior
        split = (rows["run_map"] != rows["map"]).any(axis=(1, 2, 3))
        share = np.clip(np.asarray(frame.gait, np.float64)[batch], 0.0, 1.0) * (w[:, split] > 0.0).any(axis=1)
        walking, running = share == 0.0, share == 1.0
        between = ~walking & ~running
        carried = np.empty_like(q)
        if walking.any():  # exactly what the walk prior alone gives
            carried[walking] = walk(q[walking], w[walking])
        if not walking.all():
            run = StyleCarry(*(rows[f"run_{k}"] for k in FIELDS))
            if running.any():  # the mix at share 1 (to round-off), in one carry instead of two
                carried[running] = run(q[running], w[running])
            if between.any():
                carried[between] = walk.mixed_with(run, run.bounds, q[between], w[between], share[between])
        carried = carried.astype(rotations.dtype)
        # joints the fit left fixed (Hips, legs) keep their own bits (no float64 renormalisation)
        joints = np.flatnonzero((rows["radius"] < np.pi).any(axis=0))
        out = np.array(rotations, copy=True)
        out[np.ix_(batch, joints)] = carried[:, joints]
        return out, state

    def save(self, path: Path) -> Path:
        arrays: dict[str, Any] = {"styles": np.array(self.styles), **self.carry.named(), **self.run.named("run_")}
        np.savez(path, **arrays)
        return path

    @classmethod
    def load(cls, path: Path) -> OutputPrior:
        with np.load(path) as z:
            walk = StyleCarry.read(z)
            run = StyleCarry.read(z, "run_") if "run_map" in z else walk
            return cls(tuple(str(s) for s in z["styles"]), walk, run)

    def with_styles_of(self, other: OutputPrior) -> OutputPrior:
        keep = [k for k, s in enumerate(self.styles) if s not in other.styles]
        styles = tuple(self.styles[k] for k in keep) + other.styles

        def merged(a: StyleCarry, b: StyleCarry) -> StyleCarry:
            return StyleCarry(*(np.concatenate([x[keep], y]) for x, y in zip(a.arrays, b.arrays)))

        return OutputPrior(styles, merged(self.carry, other.carry), merged(self.run, other.run))


def fit(model: LPNModel, styles: list[str] | None = None, dataset: str = DATASET) -> OutputPrior:
    """The prior of `styles` (default: all with TRAIN clips): `CARRIED` joints, walks and runs apart."""
    styles = styles or fitted_styles(model.styles(), dataset)
    clips = locomotion(dataset)
    model = model.with_own_styles()
    model.stages = model.stages.without("output_prior", "arm_coupling")  # the coupling is fitted on top
    names = model.skeleton.names
    fixed = tuple(j for j, n in enumerate(names) if n not in CARRIED)

    def fitted(style: str, gait: str) -> StyleCarry:
        inputs = [m.slice(0, FIT_FRAMES) for m in clips(INPUT_STYLE)[gait]]
        source = np.concatenate(made(model, style, inputs)).astype(np.float64)
        target = np.concatenate([m.rotations for m in clips(style)[gait]]).astype(np.float64)
        return StyleCarry.fit([source], [target], fixed, source_floor=np.radians(SOURCE_FLOOR_DEG))

    walking, running = GAITS
    walks = [fitted(s, walking) for s in styles]
    runs = [fitted(s, running) for s in styles]
    return OutputPrior(tuple(styles), StyleCarry.stack(walks), StyleCarry.stack(runs))
