"""A built-in style's arm carriage, and optionally its pace, from real TRAIN clips
(`CARRIAGE_FILE` beside the weights, written by `python -m models.lpn.carriage [--paced]`, and
`python -m models.lpn.carriage --runs=exhausted` for the run carriage;
`runtime.LPNModel` applies it).

LPN-FiLM's FiLM vectors alone barely move the arms' mean pose: driven by the validation
locomotion inputs, its active walks were read as active by the rotation style judge in 8 % of
clips and its exhausted ones in 0 %, where the real active walks carry the elbows ~30 degrees
more bent. What a style's real clips measure can be put back:

- **arm carriage** (shipped), per style and arm joint (Shoulder .. Hand, both sides): the rotation
  that takes the network's mean local rotation (driven by the `normal` TRAIN locomotion clips
  toward the style) to the mean of the style's real TRAIN locomotion clips, applied to the output
  in the parent's frame before the rotation prior; the network's state keeps its own pose.
- **run carriage** (`--runs STYLE,...`, shipped for `exhausted`), per chosen style: offsets for
  the spine, neck, head and arms (`RUN_JOINTS`) fitted on runs alone, on top of the arm carriage:
  the rotation taking the network's mean (with the arm carriage, driven by the `normal` TRAIN
  runs) to the mean of the style's real TRAIN runs; applied in proportion to the control's gait
  (0 walking: nothing). Toward exhausted the runs were otherwise upright and read as normal by
  the rotation judge (validation locomotion, 4 of 4 runs). Fitted for every style, it lowered
  elderly's content and rotation judge and active's position judge, and changed nothing for the
  others: so only where validation gained.
- **pace** (`--paced`, not shipped), per style and gait: the median Hips speed of the style's
  TRAIN walks (runs) over the `normal` style's (active 1.31 / 1.24, elderly 0.67 / 0.52). The
  derived control's velocity is multiplied by it (blended by the style weights, between walk and
  run by the gait); a control the caller gives is kept as it is. Measured on the validation
  locomotion inputs it made active walks read as active by the position judge (23 -> 100 %), but
  the slowed elderly walks and runs were read as turns (content 85 -> 77 %), and a character
  slower than the input it is driven by falls ever further behind that input's root, which a game
  driving a character by its capsule cannot use. So it is off unless a deployment fits it.

Uploaded styles get neither (pace 1, no offset): they have no walks of their own to measure.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..motion.rotations import quat_inv, quat_mean, quat_mul

CARRIAGE_FILE = "carriage.npz"
ARM_JOINTS = ("Shoulder_L", "UpperArm_L", "LowerArm_L", "Hand_L", "Shoulder_R", "UpperArm_R", "LowerArm_R", "Hand_R")
UPPER_BODY = ("Spine", "Chest", "Neck", "Head", *ARM_JOINTS)
RUN_JOINTS = UPPER_BODY  # the run carriage's joints
LOCOMOTION = {"walk": ("walk", "walk-turn-left", "walk-turn-right"), "run": ("run",)}
SKIP_FRAMES = 30  # the network's first second settles from the input's first pose: not its carriage


@dataclass(frozen=True)
class Carriage:
    """Per built-in style: pace (walk, run), the arm joints' offset rotations (xyzw) and,
    optionally, the run carriage's offsets of `RUN_JOINTS` (identity for a style without one)."""

    styles: tuple[str, ...]
    pace: np.ndarray  # (S, 2) speed factors for walking and running
    arms: np.ndarray  # (S, len(ARM_JOINTS), 4) offsets, applied as offset * rotation
    run: np.ndarray | None = None  # (S, len(RUN_JOINTS), 4) offsets at the run gait, after `arms`

    def rows(self, names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(pace, arms, run) aligned with `names`; a style not fitted gets pace 1 and no offsets
        (run: None when no style has a run carriage)."""
        pace = np.ones((len(names), 2))
        arms = np.tile((0.0, 0.0, 0.0, 1.0), (len(names), len(ARM_JOINTS), 1))
        run = None if self.run is None else np.tile((0.0, 0.0, 0.0, 1.0), (len(names), len(RUN_JOINTS), 1))
        for i, n in enumerate(names):
            if n in self.styles:
                k = self.styles.index(n)
                pace[i], arms[i] = self.pace[k], self.arms[k]
                if run is not None and self.run is not None:
                    run[i] = self.run[k]
        return pace, arms, run

    def save(self, path: Path) -> Path:
        extra = {} if self.run is None else {"run": self.run}
        np.savez(path, styles=np.array(self.styles), pace=self.pace, arms=self.arms, **extra)
        return path

    @classmethod
    def load(cls, path: Path) -> Carriage:
        with np.load(path) as z:
            run = z["run"].astype(np.float64) if "run" in z.files else None
            return cls(
                tuple(str(s) for s in z["styles"]), z["pace"].astype(np.float64), z["arms"].astype(np.float64), run
            )


def _mix(values: np.ndarray, weights: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """(B, ...) sum over styles of weight x value, plus the weights' shortfall from 1 times `rest`.
    Accumulated style by style in index order over the styles some row uses: a row's sum is its
    own nonzero terms in that order (the others add exact zeros), whatever else is in the batch."""
    w = np.asarray(weights, np.float64)
    extra = (1,) * (values.ndim - 1)
    mixed = (1.0 - w.sum(1)).reshape(-1, *extra) * rest
    for k in np.flatnonzero(w.any(0)):
        mixed = mixed + w[:, k].reshape(-1, *extra) * values[k]
    return mixed


def blend_pace(pace: np.ndarray, weights: np.ndarray, gait: np.ndarray) -> np.ndarray:
    """(B,) speed factor: the weights' mix of the styles' (walk, run) paces, the shortfall of the
    weights from 1 at pace 1 (`normal`), between walk and run by the gait (0 walk .. 1 run)."""
    mixed = _mix(pace, weights, np.ones(2))
    g = np.clip(gait, 0.0, 1.0)
    return mixed[:, 0] + (mixed[:, 1] - mixed[:, 0]) * g


def blend_arms(arms: np.ndarray, weights: np.ndarray, normal: int) -> np.ndarray:
    """(B, A, 4) offsets: the weights' normalised mix of the styles' offsets (all within tens of
    degrees of identity, one hemisphere), the shortfall from 1 given to `normal`."""
    mixed = _mix(arms, weights, arms[normal])
    return mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)


def blend_run(run: np.ndarray, weights: np.ndarray, normal: int, gait: np.ndarray) -> np.ndarray:
    """(B, R, 4) run carriage offsets: the weights' mix (as `blend_arms`), taken in proportion
    to each row's gait (0 walk: identity, 1 run: all of it; normalised linear blend, the offsets
    being within tens of degrees of identity)."""
    mixed = blend_arms(run, weights, normal)
    g = np.clip(np.asarray(gait, np.float64), 0.0, 1.0)[:, None, None]
    out = (1.0 - g) * np.array((0.0, 0.0, 0.0, 1.0)) + g * mixed
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def carry_arms(rotations: np.ndarray, offsets: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """The local rotations with each arm joint's offset applied in its parent's frame."""
    out = np.array(rotations, copy=True)
    out[:, joints] = quat_mul(offsets, rotations[:, joints]).astype(rotations.dtype)
    return out


# ---- fitting (offline) -----------------------------------------------------------------------


def median_speed(clips: list) -> float:
    """Median horizontal Hips speed (cm/s) over the frames of `clips` (Motions at 30 fps)."""
    speeds = [
        np.linalg.norm(np.diff(m.translations[:, 1][:, [0, 2]], axis=0), axis=1) * m.fps
        for m in clips
        if m.num_frames > 1
    ]
    return float(np.median(np.concatenate(speeds)))


def train_clips(dataset: str) -> Callable[[str, tuple[str, ...]], list]:
    """(style, contents) -> that style's TRAIN clips of those contents, as Motions."""
    from ..data import build_index, load_motions, select

    index = build_index([dataset])
    return lambda style, contents: load_motions(
        [c for c in select(index, split="train", style=style) if c.content in contents]
    )


def _offsets(
    model, inputs: list, real: Callable[[str], list], styles: list[str], joints: tuple[str, ...]
) -> np.ndarray:
    """(len(styles), len(joints), 4): per style, the rotation taking the mean local rotation of
    `model`'s output (driven by `inputs`, the first second skipped) to the mean of `real(style)`."""
    from ..eval.run import stylise
    from ..motion.rotation_ball import comparable

    index = [model.skeleton.names.index(j) for j in joints]
    out = np.empty((len(styles), len(joints), 4))
    for k, s in enumerate(styles):
        outs = stylise(model, inputs, [model.styles().index(s)] * len(inputs))
        made = quat_mean(comparable(np.concatenate([o.rotations[SKIP_FRAMES:] for o in outs]))[:, index], axis=0)
        mean = quat_mean(comparable(np.concatenate([m.rotations for m in real(s)]))[:, index], axis=0)
        out[k] = quat_mul(mean, quat_inv(made))
    return out


def fit(model, styles: list[str], dataset: str = "bandai-namco-2", frames: int = 300, paced: bool = False) -> Carriage:
    """The arm offsets from the network (paced, with `paced`: each style's pace from its real
    clips; otherwise pace 1) against the real clips. `model` itself is left as it was: the
    network runs on a copy carrying the pace and no offsets."""
    clips = train_clips(dataset)
    pace = np.ones((len(styles), 2))
    if paced:
        normal = {g: median_speed(clips("normal", contents)) for g, contents in LOCOMOTION.items()}
        pace = np.array([[median_speed(clips(s, LOCOMOTION[g])) / normal[g] for g in ("walk", "run")] for s in styles])
    model = model.with_own_styles()
    model.output_prior = None  # fitted on top of the carriage (`output_prior.py`): refit it after
    model.arm_coupling = None  # and the arm coupling on top of that (`arm_coupling.py`)
    model.carriage = Carriage(tuple(styles), pace, np.tile((0.0, 0.0, 0.0, 1.0), (len(styles), len(ARM_JOINTS), 1)))
    every = LOCOMOTION["walk"] + LOCOMOTION["run"]
    inputs = [m.slice(0, frames) for m in clips("normal", every)]
    return Carriage(tuple(styles), pace, _offsets(model, inputs, lambda s: clips(s, every), styles, ARM_JOINTS))


def fit_runs(
    model, carriage: Carriage, styles: list[str], dataset: str = "bandai-namco-2", frames: int = 300
) -> Carriage:
    """`carriage` with a run carriage for `styles` (the others none): offsets of `RUN_JOINTS`
    from the network with `carriage`'s pace and arms in place, driven by the `normal` TRAIN runs,
    to the style's real TRAIN runs."""
    clips = train_clips(dataset)
    model = model.with_own_styles()
    model.output_prior = model.arm_coupling = None
    model.carriage = replace(carriage, run=None)
    inputs = [m.slice(0, frames) for m in clips("normal", LOCOMOTION["run"])]
    run = np.tile((0.0, 0.0, 0.0, 1.0), (len(carriage.styles), len(RUN_JOINTS), 1))
    fitted = _offsets(model, inputs, lambda s: clips(s, LOCOMOTION["run"]), styles, RUN_JOINTS)
    for s, offsets in zip(styles, fitted):
        run[carriage.styles.index(s)] = offsets
    return replace(carriage, run=run)


def _degrees(offsets: np.ndarray) -> list[float]:
    return np.round(np.degrees(2 * np.arccos(np.clip(np.abs(offsets[:, 3]), 0.0, 1.0))), 1).tolist()


def main(argv: list[str]) -> None:
    """`[STYLE ...] [--paced]`: fit pace and arms (a run carriage in the file is dropped: it was
    fitted on top of the old arms); `--runs=STYLE,...`: add a run carriage for those styles on
    top of the file's pace and arms, which stay. Either way the output prior (`output_prior.py`),
    fitted on top of the carriage, is then to be fitted again."""
    import json
    import time

    import torch

    from ..settings import get_settings
    from .runtime import load
    from .weights import CONFIG_FILE

    torch.set_num_threads(1)
    paced = "--paced" in argv
    runs = [a.split("=", 1)[1].split(",") for a in argv if a.startswith("--runs=")]
    argv = [a for a in argv if a != "--paced" and not a.startswith("--runs=")]
    t0 = time.time()
    folder = get_settings().weights_dir / "lpn"
    model = load(folder)
    if runs:
        carriage = fit_runs(model, Carriage.load(folder / CARRIAGE_FILE), runs[0])
        carriage.save(folder / CARRIAGE_FILE)
        assert carriage.run is not None
        for s in runs[0]:
            offsets = carriage.run[carriage.styles.index(s)]
            print(f"{s:10s} run offsets (deg) {dict(zip(RUN_JOINTS, _degrees(offsets)))}")
    else:
        names = json.loads((folder / CONFIG_FILE).read_text())["styles"]
        styles = argv or [
            s for s in names if not s.startswith("d1-")
        ]  # dataset 2's styles: its clips are paired by content
        carriage = fit(model, styles, paced=paced)
        carriage.save(folder / CARRIAGE_FILE)
        for s, p, a in zip(carriage.styles, carriage.pace, carriage.arms):
            print(f"{s:10s} pace walk {p[0]:.2f} run {p[1]:.2f}  arm offsets (deg) {_degrees(a)}")
    print(f"wrote {folder / CARRIAGE_FILE} in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
