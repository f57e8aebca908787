"""Style-ERD's rotation priors as a stage: each carries only the slow part of each rotation.

Gains above 1 would scale every wobble with the pose, so a prior maps a slowly following copy
and the fast part rides on top, never magnified:

    slow_t = nlerp(slow_{t-1}, q_t, SLOW_WEIGHT)          (slow_0 = q_0)
    p_t    = slow_t^-1 q_t                                (the fast part)
    out_t  = bounds(carry(slow_t) (G p_xyz, p_w) / |.|)    (~ carry(slow_t) exp(G log p_t))

G: the map with gains capped at 1; run priors take over by run share (`gait.py`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..interface import State
from ..motion import style_carry_kernels as kernels
from ..motion.skeleton import Skeleton
from ..motion.style_carry import FIELDS, StyleCarry, carry_rows
from ..stages import Rows, StageFrame, style_rows
from .dataset import TARGET_STYLES

# the newest frame's weight in the slow copy (~4 frames behind; chosen on validation, docs/eval/ablation.md)
SLOW_WEIGHT = 0.2


def run_file(path: Path) -> Path:
    """Where the run prior of the prior in `path` is kept."""
    return path.with_name(f"{path.stem}_run{path.suffix}")


def merged(carry: StyleCarry, at: Sequence[int], other: StyleCarry) -> StyleCarry:
    """`carry` with its styles `at` (indices) replaced by `other`'s, in turn."""
    arrays = [np.array(a) for a in carry.arrays]
    for a, b in zip(arrays, other.arrays):
        a[list(at)] = b
    return StyleCarry(*arrays)


@dataclass(frozen=True)
class SlowPrior:
    """The stage: per fitted style, `carry` for every frame and `run` (None: none) for running
    frames; joint `hips` (>= 0) without its heading. `fast` (S, J, 3, 3): fast-part gains where not
    `carry`'s own capped (an upload's source floor guards the slow map, not the fast part)."""

    styles: tuple[str, ...]
    carry: StyleCarry
    run: StyleCarry | None = None
    hips: int = -1
    fast: np.ndarray | None = None

    @property
    def gains(self) -> np.ndarray:
        """(S, J, 3, 3) the fast part's gains."""
        return self.carry.damping if self.fast is None else self.fast

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """Both carries' arrays (`run_` prefixed), fast gains, clamp and `plain` joints, aligned with `styles`."""
        J, eye = skeleton.num_joints, np.eye(3)
        arrays = carry_rows({"": self.carry, "run_": self.run or self.carry}, J)
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
        share = np.zeros(len(w)) if self.run is None else np.asarray(frame.gait, np.float64)
        r = rows  # read out one by one: the step runs at batch 1 too, where a generator costs a microsecond
        bounds = (r["mean"], r["mean"], r["bounds"], r["radius"])
        walk = (r["source"], r["mean"], r["map"], r["radius"])
        run = (r["run_source"], r["run_mean"], r["run_map"], r["run_radius"])
        priors = kernels.SlowPriors(walk, run, bounds, bounds, r["gain"], r["plain"])
        out, slow = kernels.carry_slow(frame.rotations, state["slow"], SLOW_WEIGHT, w, share, priors, self.hips)
        return out, {"slow": slow}

    def save(self, path: Path) -> Path:
        self.carry.save(path)
        if self.run is not None:
            self.run.save(run_file(path))
        return path

    @classmethod
    def load(cls, path: Path, hips: int = -1) -> SlowPrior:
        """The prior in `path` (fitted for every target style), its run prior beside it if there."""
        run = run_file(path)
        return cls(TARGET_STYLES, StyleCarry.load(path), StyleCarry.load(run) if run.exists() else None, hips)

    def stacked(self, others: Sequence[tuple[str, SlowPrior]]) -> SlowPrior:
        """This prior with each of `others` (name, one style's prior) as one more style."""
        carry = StyleCarry.stack([self.carry, *(o.carry for _, o in others)])
        run = None if self.run is None else StyleCarry.stack([self.run, *(o.run or o.carry for _, o in others)])
        fast = (
            None
            if self.fast is None and all(o.fast is None for _, o in others)
            else np.concatenate([self.gains, *(o.gains for _, o in others)])
        )
        return replace(self, styles=self.styles + tuple(n for n, _ in others), carry=carry, run=run, fast=fast)

    def with_styles_of(self, other: SlowPrior) -> SlowPrior:
        at = [self.styles.index(s) for s in other.styles]
        run = None if self.run is None or other.run is None else merged(self.run, at, other.run)
        return replace(self, carry=merged(self.carry, at, other.carry), run=run, fast=None)
