"""A style's arm carriage from its real TRAIN clips, the same fit for every style (`python -m
models.lpn fit --stages carriage` writes `CARRIAGE_FILE`).

FiLM vectors alone barely move the arms' mean pose, where real styles differ in it: per style and
arm joint, the rotation from the network's mean (on neutral locomotion) to the style's real mean,
walks and runs apart (`models.motion.gait_split`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..eval.run import DATASET, INPUT_STYLE
from ..interface import State
from ..motion.coupling import GAITS
from ..motion.gait_split import split_by_gait
from ..motion.rotations import quat_inv, quat_mean, quat_mul
from ..motion.skeleton import Motion, Skeleton
from ..stages import Rows, StageFrame, Stateless, style_rows

if TYPE_CHECKING:
    from .runtime import LPNModel

CARRIAGE_FILE = "carriage.npz"
ARM_JOINTS = ("Shoulder_L", "UpperArm_L", "LowerArm_L", "Hand_L", "Shoulder_R", "UpperArm_R", "LowerArm_R", "Hand_R")
UPPER_BODY = ("Spine", "Chest", "Neck", "Head", *ARM_JOINTS)
SKIP_FRAMES = 30  # the network's first second settles from the input's first pose: not its carriage


@dataclass(frozen=True)
class Carriage(Stateless):
    """The stage: per style, the arm joints' offset rotations (xyzw)."""

    styles: tuple[str, ...]
    arms: np.ndarray  # (S, len(ARM_JOINTS), 4) offsets, applied as offset * rotation

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """The offsets aligned with `styles` (a style not fitted gets none) and the arm joints."""
        rows = style_rows(self.styles, styles, arms=(self.arms, np.tile((0.0, 0.0, 0.0, 1.0), (len(ARM_JOINTS), 1))))
        return {**rows, "joints": np.array([skeleton.names.index(j) for j in ARM_JOINTS], np.int64)}

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        offsets = blend_arms(rows["arms"], frame.weights, frame.base)
        return carry_arms(frame.rotations, offsets, rows["joints"]), state

    def with_styles_of(self, other: Carriage) -> Carriage:
        keep = [k for k, s in enumerate(self.styles) if s not in other.styles]
        return Carriage(
            tuple(self.styles[k] for k in keep) + other.styles, np.concatenate([self.arms[keep], other.arms])
        )

    def save(self, path: Path) -> Path:
        np.savez(path, styles=np.array(self.styles), arms=self.arms)
        return path

    @classmethod
    def load(cls, path: Path) -> Carriage:
        with np.load(path) as z:
            return cls(tuple(str(s) for s in z["styles"]), z["arms"].astype(np.float64))


def _mix(values: np.ndarray, weights: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """(B, ...) sum of weight x value plus the shortfall times `rest`, in style order: batch-independent."""
    w = np.asarray(weights, np.float64)
    extra = (1,) * (values.ndim - 1)
    mixed = (1.0 - w.sum(1)).reshape(-1, *extra) * rest
    for k in np.flatnonzero(w.any(0)):
        mixed = mixed + w[:, k].reshape(-1, *extra) * values[k]
    return mixed


def blend_arms(arms: np.ndarray, weights: np.ndarray, normal: int) -> np.ndarray:
    """(B, A, 4) the weights' normalised mix of the offsets (one hemisphere), shortfall to `normal`."""
    mixed = _mix(arms, weights, arms[normal])
    return mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)


def carry_arms(rotations: np.ndarray, offsets: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """The local rotations with each arm joint's offset applied in its parent's frame."""
    out = np.array(rotations, copy=True)
    out[:, joints] = quat_mul(offsets, rotations[:, joints]).astype(rotations.dtype)
    return out


# ---- fitting (offline) -----------------------------------------------------------------------


def locomotion(dataset: str) -> Callable[[str], dict[str, list]]:
    """style -> its TRAIN clips of `dataset` by gait (`GAITS`), split by its own speeds; loaded once."""
    from ..data import build_index, load_motions, select

    index = build_index([dataset])

    @functools.cache
    def clips(style: str) -> dict[str, list]:
        return dict(zip(GAITS, split_by_gait(load_motions(select(index, split="train", style=style)))))

    return clips


def every_gait(clips: dict[str, list]) -> list:
    return [m for gait in GAITS for m in clips[gait]]


def fitted_styles(names: list[str], dataset: str) -> list[str]:
    """The styles of `names` with TRAIN clips in `dataset`: what the fits fit by default."""
    from ..data import build_index, select

    have = {c.style for c in select(build_index([dataset]), split="train")}
    return [n for n in names if n in have]


def made(model: LPNModel, style: str, inputs: list[Motion]) -> list[np.ndarray]:
    """`model`'s rotations toward `style` per input, the first second skipped: what stages are fitted on."""
    from ..eval.run import stylise

    return [o.rotations[SKIP_FRAMES:] for o in stylise(model, inputs, [model.styles().index(style)] * len(inputs))]


def _offsets(
    model: LPNModel, inputs: list, real: Callable[[str], list], styles: list[str], joints: tuple[str, ...]
) -> np.ndarray:
    """(styles, joints, 4) per style, the rotation from the mean of `made` to the real mean."""
    from ..motion.rotation_ball import comparable

    index = [model.skeleton.names.index(j) for j in joints]
    out = np.empty((len(styles), len(joints), 4))
    for k, s in enumerate(styles):
        output = quat_mean(comparable(np.concatenate(made(model, s, inputs)))[:, index], axis=0)
        mean = quat_mean(comparable(np.concatenate([m.rotations for m in real(s)]))[:, index], axis=0)
        out[k] = quat_mul(mean, quat_inv(output))
    return out


def fit(model: LPNModel, styles: list[str] | None = None, dataset: str = DATASET, frames: int = 300) -> Carriage:
    """The arm offsets of `styles` (default: all with TRAIN clips); `model` is left as it was."""
    styles = styles or fitted_styles(model.styles(), dataset)
    clips = locomotion(dataset)
    model = model.with_own_styles()
    # the output prior and the arm coupling are fitted on top of the carriage: refit them after
    identity = Carriage(tuple(styles), np.tile((0.0, 0.0, 0.0, 1.0), (len(styles), len(ARM_JOINTS), 1)))
    model.stages = model.stages.replace(carriage=identity, output_prior=None, arm_coupling=None)
    inputs = [m.slice(0, frames) for m in every_gait(clips(INPUT_STYLE))]
    return Carriage(tuple(styles), _offsets(model, inputs, lambda s: every_gait(clips(s)), styles, ARM_JOINTS))
