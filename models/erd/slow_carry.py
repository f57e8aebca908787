"""Style-ERD's rotation priors as a stage: each carries only the slow part of each rotation.

Gains above 1 would scale every wobble with the pose, so a prior maps a slowly following copy
and the fast part rides on top, never magnified:

    slow_t = nlerp(slow_{t-1}, q_t, SLOW_WEIGHT)          (slow_0 = q_0)
    p_t    = slow_t^-1 q_t                                (the fast part)
    out_t  = bounds(carry(slow_t) (G p_xyz, p_w) / |.|)    (~ carry(slow_t) exp(G log p_t))

G: the map with gains capped at 1; run and stand priors take over by gait share (`gait.py`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypedDict

import numpy as np

from ..interface import State
from ..motion import style_carry_kernels as kernels
from ..motion.skeleton import Skeleton
from ..motion.style_carry import FIELDS, StyleCarry, carry_rows
from ..stages import Rows, StageFrame, style_rows
from .dataset import TARGET_STYLES

# the newest frame's weight in the slow copy (~4 frames behind; chosen on validation, docs/eval/ablation.md)
SLOW_WEIGHT = 0.2


# the gaits a prior may have a carry of its own for, by their rows' prefix (the field and file
# suffix without the underscore: `run`, `output_prior_run.npz`)
GAITS = ("run_", "stand_")


def gait_file(path: Path, gait: str) -> Path:
    """Where the `gait` prior (`GAITS`) of the prior in `path` is kept."""
    return path.with_name(f"{path.stem}_{gait.rstrip('_')}{path.suffix}")


class Gaits(TypedDict):  # a SlowPrior's gait fields, as keyword arguments
    run: StyleCarry | None
    stand: StyleCarry | None


def by_gait(carry_of: Callable[[str], StyleCarry | None]) -> Gaits:
    """A `SlowPrior`'s gait fields, each `carry_of` its rows' prefix: the one place a prefix of
    `GAITS` meets its field."""
    return Gaits(run=carry_of(GAITS[0]), stand=carry_of(GAITS[1]))


def merged(carry: StyleCarry, at: Sequence[int], other: StyleCarry) -> StyleCarry:
    """`carry` with its styles `at` (indices) replaced by `other`'s, in turn."""
    arrays = [np.array(a) for a in carry.arrays]
    for a, b in zip(arrays, other.arrays):
        a[list(at)] = b
    return StyleCarry(*arrays)


@dataclass(frozen=True)
class SlowPrior:
    """The stage: per fitted style, `carry` for every frame, `run` and `stand` (None: none) for
    running and standing frames; joint `hips` (>= 0) without its heading. `fast` (S, J, 3, 3):
    fast-part gains where not `carry`'s own capped (an upload's source floor guards the slow map,
    not the fast part)."""

    styles: tuple[str, ...]
    carry: StyleCarry
    run: StyleCarry | None = None
    hips: int = -1
    fast: np.ndarray | None = None
    stand: StyleCarry | None = None

    @property
    def gains(self) -> np.ndarray:
        """(S, J, 3, 3) the fast part's gains."""
        return self.carry.damping if self.fast is None else self.fast

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """Every carry's arrays (`run_`, `stand_` prefixed), fast gains, clamp and `plain` joints,
        aligned with `styles`."""
        J, eye = skeleton.num_joints, np.eye(3)
        arrays = carry_rows({"": self.carry, **{g: self.gait(g) or self.carry for g in GAITS}}, J)
        rows = style_rows(self.styles, styles, gain=(self.gains, np.tile(eye, (J, 1, 1))), **arrays)
        aligned = StyleCarry(*(rows[k] for k in FIELDS))
        whole = np.all(aligned.map == eye, axis=(-1, -2)) & np.all(aligned.source == aligned.mean, axis=-1)
        return rows | {"bounds": aligned.bounds.map, "plain": whole}

    def init_state(self, batch: int) -> State:
        """The slow copy (zeros: unset, the session's next frame starts it)."""
        return {"slow": np.zeros((batch, self.carry.mean.shape[1], 4))}

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        """The frame carried in one compiled pass (`style_carry_kernels.carry_slow_batch`)."""
        w = np.asarray(frame.weights, np.float64)
        lo, hi = -float(self.stand is not None), float(self.run is not None)  # no prior of its own: the walk's
        share = np.clip(np.asarray(frame.gait, np.float64), lo, hi)
        r = rows  # read out one by one: the step runs at batch 1 too, where a generator costs a microsecond
        bounds = (r["mean"], r["mean"], r["bounds"], r["radius"])
        walk = (r["source"], r["mean"], r["map"], r["radius"])
        run = (r["run_source"], r["run_mean"], r["run_map"], r["run_radius"])
        stand = (r["stand_source"], r["stand_mean"], r["stand_map"], r["stand_radius"])
        priors = kernels.SlowPriors(walk, run, stand, bounds, r["gain"], r["plain"])
        out, slow = kernels.carry_slow(frame.rotations, state["slow"], SLOW_WEIGHT, w, share, priors, self.hips)
        return out, {"slow": slow}

    def save(self, path: Path) -> Path:
        self.carry.save(path)
        for gait in GAITS:
            if (carry := self.gait(gait)) is not None:
                carry.save(gait_file(path, gait))
        return path

    def gait(self, prefix: str) -> StyleCarry | None:
        """The carry of the gait with this rows' prefix (`GAITS`), None where it has none."""
        return getattr(self, prefix.rstrip("_"))

    @classmethod
    def load(cls, path: Path, hips: int = -1) -> SlowPrior:
        """The prior in `path` (fitted for every target style), its gaits' priors beside it if there."""
        gaits = by_gait(lambda g: StyleCarry.load(f) if (f := gait_file(path, g)).exists() else None)
        return cls(TARGET_STYLES, StyleCarry.load(path), hips=hips, **gaits)

    def stacked(self, others: Sequence[tuple[str, SlowPrior]]) -> SlowPrior:
        """This prior with each of `others` (name, one style's prior) as one more style."""
        carry = StyleCarry.stack([self.carry, *(o.carry for _, o in others)])

        def gait(g: str) -> StyleCarry | None:  # an upload without its own takes its walk carry
            own = self.gait(g)
            return None if own is None else StyleCarry.stack([own, *(o.gait(g) or o.carry for _, o in others)])

        fast = (
            None
            if self.fast is None and all(o.fast is None for _, o in others)
            else np.concatenate([self.gains, *(o.gains for _, o in others)])
        )
        styles = self.styles + tuple(n for n, _ in others)
        return replace(self, styles=styles, carry=carry, fast=fast, **by_gait(gait))

    def with_styles_of(self, other: SlowPrior) -> SlowPrior:
        at = [self.styles.index(s) for s in other.styles]

        def gait(g: str) -> StyleCarry | None:
            own, theirs = self.gait(g), other.gait(g)
            return None if own is None or theirs is None else merged(own, at, theirs)

        return replace(self, carry=merged(self.carry, at, other.carry), fast=None, **by_gait(gait))
