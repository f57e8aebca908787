"""Knees and elbows kept on their hinge at no less than their least real bend: a stage after a
method's network.

A network deciding rotations (Style-ERD, LPN-FiLM) bends a knee or elbow past straight for a few
frames where a style pulls the limb far. Real limbs never do, so each output's swing becomes its
bend about the hinge axis, held at the floor (`hinge_kernels.floor_bends`), twist kept. Fitted
once per rig from every dataset-2 TRAIN clip (as `python -m models.lti hinges`), it runs for every
style alike, uploads included.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..interface import State
from ..stages import Rows, StageFrame, StageSpec, Stateless
from .hinge import Hinges, fit_hinges, kernel_floor
from .hinge_kernels import floor_bends
from .skeleton import Skeleton

FLOOR_FILE = "hinge_floor.npz"
DATASET = "bandai-namco-2"  # the rig's real rotations the floor is fitted from, every style


class HingeFloor(Stateless):
    """The stage: per joint its bone axis, hinge axis and floor, as `floor_bends` takes them."""

    def __init__(self, skeleton: Skeleton, hinges: Hinges) -> None:
        if hinges.floor is None:
            raise ValueError("hinges fitted without floors")
        self.hinges = hinges
        self.arrays = kernel_floor(skeleton, hinges)

    def __call__(self, rotations: np.ndarray) -> np.ndarray:
        """(..., J, 4) local rotations -> a float64 copy with every hinge held at its floor."""
        q = np.array(rotations, np.float64).reshape(-1, *rotations.shape[-2:])
        return floor_bends(q, *self.arrays).reshape(rotations.shape)

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        return {}  # the same floor for every style

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        return self(frame.rotations).astype(frame.rotations.dtype, copy=False), state

    def save(self, path: Path) -> Path:
        return self.hinges.save(path)


def fit_floor(skeleton: Skeleton) -> Hinges:
    """The rig's hinge joints and floors from every dataset-2 TRAIN clip, every style."""
    from ..data import build_index, load_motions, select

    clips = select(build_index([DATASET]), dataset=DATASET, split="train")
    return fit_hinges(skeleton, np.concatenate([m.rotations for m in load_motions(clips)]))


# the stage as a method declares it (`models.stages.StageSpec`): `python -m models.<method> fit`
STAGE = StageSpec(
    "hinge_floor",
    FLOOR_FILE,
    lambda path, skeleton: HingeFloor(skeleton, Hinges.load(path)),
    lambda model, _: HingeFloor(model.skeleton, fit_floor(model.skeleton)),
)
