"""Planted feet for every method: the root travels by the feet on the ground, the legs hold them.

A style model changes how the legs move and how fast the root travels, and nothing makes the two
agree, so planted feet slide. Per frame, causally, on the model rig:
1. Root: keeps the model's path (`follow=0`) while the legs do the work; past a quarter of
   `max_offset` a leash lets the root give way against the held points' motion. With `give`,
   the root also takes, on the frame, whatever a held foot still on the ground would need past
   `give` (the shortest move that keeps every such hold within it; two held feet the animation
   spreads further apart: the one it moves less, the other as near as that allows), at most
   `give_speed`, the holds taking the rest up to their let-go: a hold no longer lets go and snaps
   back because the animation's foot slid under a body that did not follow (Kovar et al. 2002:
   the root adjusted, then the legs' IK).
2. Contact: a toe or ankle within `margin` of its floor touching down slowly enough, or the
   model's `hints`. The toe is held whenever it is down, else the ankle. Each floor follows its
   point down at once and up by `floor_rise` per second (networks' feet float or sink); a hinted
   foot lifts it at once to `feet_kernels.HINT_FLOOR_RISE` below it (the hint says the ground is near).
3. Hold: an offset collects the opposite of the held point's motion and two-bone IK moves the
   ankle by it; past `max_offset` it lets go, unless the hints call the foot down: then it is
   kept (the leash has the root follow one held foot; two the animation pulls apart grow up to
   `hint_offset`). Released, it fades by `decay` per frame. Soft IK eases the last `soft` cm of reach.

One compiled pass (`feet_kernels.plant_feet`); the state is plain `feet_*` arrays, so it joins a
model's state, snapshots and resumes with it.
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
    """Plants the feet of one rig (see the module docstring). Lengths in the rig's units (cm on
    the Bandai Namco rig), speeds per second at `fps`."""

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
    # a held foot the hints call down lets go only this far from the animation (None:
    # `max_offset`): where the model or its input says the foot is planted, it is kept
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
        """A planter for `skeleton`, whose root translation is its Hips position (the Hips are the
        hip joints' parent). `floors`: ankle and toe height of a flat foot on the ground."""
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
        """`state` with fresh planter keys where it has none (a snapshot from before the planter):
        such a session plants from its next frame on."""
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
        """The model's frame (root (B, 3), local rotations (B, J, 4)) with its feet planted:
        (root, rotations, planted legs (B, 2) bool, the planter's new state). `state` is not changed.
        Sessions with `active` False (B,) get their frame back as it is: a style at intensity 0
        returns the input, planted or not. `hints` (B, 2): the model's own contacts; a hinted foot
        on the ground plants however fast the animation moves it."""
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
        """A whole clip (F, 3), (F, J, 4) planted frame by frame as a stream would be (offline
        paths use this to match the streaming step): (root, rotations, planted legs (F, 2))."""
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
    """A method's last stage: `frame`'s feet planted by `planter`, its contacts the hints, the
    planter's state read from `before`. Returns the planted frame (the planted legs its contacts,
    arrays of the frame's dtype) and the planter's new state entries. Methods step through it
    (`step_unplanted` then this) so a stage can go between them (the unseen-content fade)."""
    root, rotations, contacts, feet = planter(
        {k: before[k] for k in STATE_SHAPES}, frame.root, frame.rotations, hints=frame.contacts
    )
    dtype = np.asarray(frame.root).dtype
    return FrameBatch(root.astype(dtype, copy=False), rotations.astype(dtype, copy=False), contacts), feet
