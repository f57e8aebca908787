"""Planted feet for every method: the root travels by the feet on the ground, the legs hold them.

A style model changes how the legs move and how fast the root travels, and nothing makes the two
agree, so planted feet slide. Per frame, causally: the root keeps the model's path, giving way
past a quarter of `max_offset` (and, with `give`, taking what a hold needs past `give`: Kovar et
al. 2002); a toe or ankle touching down slowly near its floor, or hinted by the model, is held by
two-bone IK until its offset passes `max_offset` (hinted: `hint_offset`), then fades by `decay`.
Floors follow each point down at once and up by `floor_rise` per second.

One compiled pass (`feet_kernels.plant_feet`); the state is plain `feet_*` arrays in the model's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..interface import FrameBatch, State
from . import feet_kernels
from .assets import BANDAI_NAMCO_ANKLE_FLOOR, BANDAI_NAMCO_TOE_FLOOR, bandai_namco_skeleton
from .skeleton import Skeleton

LEGS = (("UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L"), ("UpperLeg_R", "LowerLeg_R", "Foot_R", "Toes_R"))
"""The Bandai Namco (model rig) legs: hip joint, knee, ankle, toe, left then right."""
LEG_JOINTS = LEGS[0] + LEGS[1]  # every leg joint, left then right

STATE_SHAPES: dict[str, tuple[tuple[int, ...], type]] = {
    "feet_started": ((), bool),
    "feet_root": ((3,), np.float64),
    "feet_model_root": ((3,), np.float64),
    "feet_rel": ((2, 2, 3), np.float64),
    "feet_contact": ((2,), bool),
    "feet_point": ((2,), np.int64),
    "feet_offset": ((2, 3), np.float64),
    "feet_floor": ((2, 2), np.float64),
}
"""Per session: whether a frame was seen; the last planted and model roots; the ankle and toe of
each leg relative to the root; planted legs; held point (0 ankle, 1 toe); the legs' IK offsets;
each leg's ankle and toe floor heights as the planter sees them."""


@dataclass(frozen=True)
class FootPlanter:
    """Plants the feet of one rig (module docstring); lengths in rig units, speeds per second."""

    hips: int
    chains: np.ndarray  # (2, 4) int64: hip joint, knee, ankle, toe per leg
    offsets: np.ndarray  # (J, 3) float64 bone offsets
    floors: np.ndarray  # (2,) ankle and toe height when the foot is flat on the ground
    fps: float
    margin: float = 3.0  # above a point's floor height it is off the ground
    floor_rise: float = 3.0  # per second: how fast a point's floor follows it up
    onset_speed: float = 60.0  # a foot faster than this over the ground does not plant
    max_offset: float = 15.0  # a hold this far from the animation lets go (without a hint)
    decay: float = 0.7  # per frame, of a released foot's offset
    follow: float = 0.0  # share of the root motion taken from the planted feet (0: the path is the model's)
    soft: float = 5.0  # the last this much of a leg's reach is eased (feet_kernels.soft_reach): no knee pops
    hint_speed: float = math.inf  # a hinted foot faster than this over the ground does not plant
    give: float = 0.0  # past this the root, not the leg, takes a held foot's hold (0: never; below max_offset)
    give_speed: float = math.inf  # per second: the most the root moves off its path for `give`
    # a held foot the hints call down lets go only this far (None: `max_offset`)
    hint_offset: float | None = None
    _params: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(
            self,
            "_params",
            (
                np.int64(self.hips),
                np.ascontiguousarray(self.chains, np.int64),
                np.ascontiguousarray(self.offsets, np.float64),
                np.ascontiguousarray(self.floors, np.float64),
                float(self.margin),
                float(self.floor_rise),
                float(self.onset_speed),
                float(self.max_offset),
                float(self.decay),
                float(self.follow),
                float(self.soft),
                float(self.fps),
                float(self.hint_speed),
                float(self.give),
                float(self.give_speed),
                float(self.max_offset if self.hint_offset is None else self.hint_offset),
            ),
        )

    @classmethod
    def for_skeleton(
        cls,
        skeleton: Skeleton,
        floors: tuple[float, float],
        fps: float,
        legs: tuple[tuple[str, ...], ...] = LEGS,
        **settings: float,
    ) -> FootPlanter:
        """A planter for `skeleton`; `floors`: a flat foot's ankle and toe heights."""
        chains = np.array([[skeleton.index(n) for n in leg] for leg in legs], dtype=np.int64)
        hips = int(skeleton.parents[chains[0, 0]])
        if any(int(skeleton.parents[c[0]]) != hips for c in chains):
            raise ValueError("both legs must hang from one hips joint")
        return cls(
            hips, chains, np.asarray(skeleton.offsets, np.float64), np.asarray(floors, np.float64), fps, **settings
        )

    def init_state(self, batch: int) -> dict[str, np.ndarray]:
        return {k: np.zeros((batch, *shape), dtype) for k, (shape, dtype) in STATE_SHAPES.items()}

    def upgrade_state(self, state: dict[str, np.ndarray], batch: int) -> dict[str, np.ndarray]:
        """`state` with fresh planter keys where it lacks them (it plants from the next frame)."""
        if all(k in state for k in STATE_SHAPES):
            return state
        return {**self.init_state(batch), **state}

    def __call__(
        self,
        state: dict[str, np.ndarray],
        root: np.ndarray,
        rotations: np.ndarray,
        active: np.ndarray | None = None,
        hints: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """The frame with its feet planted: (root, rotations, planted legs (B, 2), new state)."""
        root = np.ascontiguousarray(root, np.float64)
        B = len(root)
        active = np.ones(B, bool) if active is None else np.ascontiguousarray(active, bool)
        hints = np.zeros((B, 2), bool) if hints is None else np.ascontiguousarray(hints, bool)
        out_rot = np.array(rotations, dtype=np.float64, order="C")
        if (
            root.shape != (B, 3)
            or out_rot.shape != (B, len(self.offsets), 4)
            or active.shape != (B,)
            or hints.shape != (B, 2)
        ):
            raise ValueError(
                f"root must be (B, 3), rotations (B, {len(self.offsets)}, 4), active (B,) and hints "
                f"(B, 2), got {root.shape}, {out_rot.shape}, {active.shape} and {hints.shape}"
            )
        for key, (shape, _) in STATE_SHAPES.items():
            if state[key].shape != (B, *shape):
                raise ValueError(f"state[{key!r}] must be {(B, *shape)}, got {state[key].shape}")
        new = {
            "feet_started": np.ones(B, bool),
            "feet_root": np.empty((B, 3)),
            "feet_model_root": root.copy(),
            "feet_rel": np.empty((B, 2, 2, 3)),
            "feet_contact": np.empty((B, 2), bool),
            "feet_point": np.empty((B, 2), np.int64),
            "feet_offset": np.empty((B, 2, 3)),
            "feet_floor": np.empty((B, 2, 2)),
        }
        s: dict[str, np.ndarray] = {k: np.ascontiguousarray(state[k], dtype) for k, (_, dtype) in STATE_SHAPES.items()}
        before, after = (feet_kernels.Feet(*(d[k] for k in STATE_SHAPES)) for d in (s, new))
        feet_kernels.plant_feet(root, out_rot, active, hints, before, after, out_rot, self._params)
        return new["feet_root"].copy(), out_rot, new["feet_contact"].copy(), new

    def clip(
        self, root: np.ndarray, rotations: np.ndarray, hints: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A whole clip planted frame by frame as a stream would be: (root, rotations, planted legs)."""
        state = self.init_state(1)
        out_root, out_rot = np.empty((len(root), 3)), np.empty((len(root), len(self.offsets), 4))
        contacts = np.empty((len(root), 2), bool)
        for t in range(len(root)):
            r, q, c, state = self(
                state, root[t : t + 1], rotations[t : t + 1], hints=None if hints is None else hints[t : t + 1]
            )
            out_root[t], out_rot[t], contacts[t] = r[0], q[0], c[0]
        return out_root, out_rot, contacts


def model_rig_planter(fps: float, **settings: float) -> FootPlanter:
    """The planter of the models' own (Bandai Namco) rig, which every method streams on."""
    return FootPlanter.for_skeleton(
        bandai_namco_skeleton(), (BANDAI_NAMCO_ANKLE_FLOOR, BANDAI_NAMCO_TOE_FLOOR), fps, LEGS, **settings
    )


def plant_frame(planter: FootPlanter, frame: FrameBatch, before: State) -> tuple[FrameBatch, State]:
    """A method's last stage, after `step_unplanted` (so the fade can go between): (frame, state)."""
    root, rotations, contacts, feet = planter(
        {k: before[k] for k in STATE_SHAPES}, frame.root, frame.rotations, hints=frame.contacts
    )
    dtype = np.asarray(frame.root).dtype
    return FrameBatch(root.astype(dtype, copy=False), rotations.astype(dtype, copy=False), contacts), feet
