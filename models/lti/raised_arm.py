"""A raised hand that does not wave: its arm carried toward how the real style holds a raised arm.

    .venv/bin/python -m models.lti.raised_arm      # fit every style -> models/weights/lti/raised_arm.npz

Why: the translators are linear maps identified over every content, walks most of all, and an
arm raised above the shoulder lies far from where they were fitted: the translated hand does not
rise as the style's does, and the content judge then reads a raise-up as a wave (model card).

What: per output style, a `StyleCarry` (`models.motion.style_carry`) from the rotations the
translator makes of the neutral TRAIN clips to the style's real TRAIN clips, both on the frames
where a hand is raised and calm (`models.motion.hands.calm_frames`: the hand's height over its
shoulder and its sway, measured on the motion; no content label picks the clips), fitted for
each side apart (each arm's joints, Shoulder to Hand, from its own side's fit), with its gains
capped at 1 (`StyleCarry.damping`: with the full gains the carry magnified the raised hand's
sway). While the input's hand is raised and calm (raise share times one minus the wave share:
what `waving_arm.py` leaves), that arm is mixed toward the carried one by the share, inside the
compiled step (`kernels.carry_raised_arms`). A style without a fit (an uploaded one) is left as
the translator made it.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np

from ..motion.bn_skeleton import BN_JOINTS, HIPS, NUM_JOINTS, ROOT
from ..motion.feet import LEG_JOINTS
from ..motion.hands import RAISE_RAMP_CM, WAVE_RAMP_CM_S, calm_frames, raise_share, wave_share
from ..motion.rotation_ball import comparable
from ..motion.style_carry import StyleCarry, real_train_frames
from .kernels import RaisedArm

FILE = "raised_arm.npz"
ARM_JOINTS = ("Shoulder", "UpperArm", "LowerArm", "Hand")
FIT_FRAMES = 240
_ARM = [np.array([BN_JOINTS.index(f"{j}_{side}") for j in ARM_JOINTS]) for side in "LR"]


def shares(offsets: np.ndarray, swayed: np.ndarray) -> np.ndarray:
    """(B, 2) how far each arm is moved: its hand's raise share times one minus its wave share,
    from the input's `hand_offsets` (B, 2, 3) and sway (B, 2)."""
    return raise_share(np.asarray(offsets)[..., 1]) * (1.0 - wave_share(swayed))


def carried(carry: StyleCarry, rotations: np.ndarray, weights: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(B, J, 4) `rotations` with each side's arm moved toward what `carry` makes of it (style
    weights (B, S)) by that side's `share` (B, 2): a normalised blend of the quaternions. Rows
    at share 0 are returned as they are."""
    if not np.any(share > 0.0):
        return rotations
    out = np.array(rotations, np.float64)
    for side, joints in enumerate(_ARM):
        rows = np.flatnonzero(share[:, side] > 0.0)
        if rows.size == 0:
            continue
        a = out[np.ix_(rows, joints)]
        b = carry(out[rows], weights[rows], hips=HIPS)[:, joints]
        b = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0.0, -b, b)
        s = share[rows, side][:, None, None]
        mixed = (1.0 - s) * a + s * b
        out[np.ix_(rows, joints)] = mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)
    return out


def settings(carries: list[StyleCarry | None]) -> RaisedArm:
    """The record the compiled step takes (`kernels.RaisedArm`) for the styles' carries, in style
    order (None: a style without one)."""
    fitted = [c for c in carries if c is not None]
    both = StyleCarry.stack(fitted) if fitted else StyleCarry(*_no_carry())
    rows, k = [], 0
    for c in carries:
        rows.append(k if c is not None else -1)
        k += c is not None
    source, mean, lin, radius = (np.ascontiguousarray(a, np.float64) for a in both.arrays)
    return RaisedArm(
        source,
        mean,
        lin,
        radius,
        np.array(rows, np.int64),
        np.ascontiguousarray(_ARM, np.int64),
        np.array(RAISE_RAMP_CM, np.float64),
        np.array(WAVE_RAMP_CM_S, np.float64),
    )


def _no_carry() -> tuple[np.ndarray, ...]:
    return (
        np.zeros((0, NUM_JOINTS, 4)),
        np.zeros((0, NUM_JOINTS, 4)),
        np.zeros((0, NUM_JOINTS, 3, 3)),
        np.zeros((0, NUM_JOINTS)),
    )


def load(folder: Path) -> dict[str, StyleCarry]:
    """Per style, its one-style carry from `folder`/`FILE` (none when the file is missing)."""
    path = Path(folder) / FILE
    if not path.exists():
        return {}
    with np.load(path) as z:
        styles = [str(s) for s in z["styles"]]
        arrays = [np.ascontiguousarray(z[k], np.float64) for k in ("source", "mean", "map", "radius")]
    return {s: StyleCarry(*(a[k : k + 1] for a in arrays)) for k, s in enumerate(styles)}


def save(carries: dict[str, StyleCarry], folder: Path) -> Path:
    path = Path(folder) / FILE
    both = StyleCarry.stack(list(carries.values()))
    np.savez(path, styles=np.array(list(carries)), source=both.source, mean=both.mean, map=both.map, radius=both.radius)
    return path


def fit(model) -> dict[str, StyleCarry]:
    """Per style of the `LTIStyleModel` (its raised arms off): the carry described above, fitted
    the same way for every style from all its TRAIN clips."""
    from ..data import build_index, load_motions, select
    from ..eval.run import DATASET, INPUT_STYLE, stylise

    train = select(build_index([DATASET]), split="train")
    every_content = tuple(sorted({c.content for c in train}))  # which frames count is measured, not named
    inputs = [m.slice(0, FIT_FRAMES) for m in load_motions([c for c in train if c.style == INPUT_STYLE])]
    styles = model.styles()
    outs = stylise(model, [m for _ in styles for m in inputs], [k for k in range(len(styles)) for _ in inputs])
    n = len(inputs)
    made = [comparable(np.concatenate([o.rotations for o in outs[k * n : (k + 1) * n]])) for k in range(len(styles))]
    clamped = (HIPS,) + tuple(BN_JOINTS.index(j) for j in LEG_JOINTS)
    sides = []
    for side in (0, 1):
        frames = functools.partial(calm_frames, side=side)
        chosen = np.concatenate([frames(m) for m in inputs])
        real = real_train_frames(styles, every_content, frames)
        sides.append(StyleCarry.fit([q[chosen] for q in made], real, (ROOT,), clamp_only=clamped))
    every = list(range(len(styles)))
    both = sides[0].with_maps_of(sides[1], every, list(_ARM[1]))
    damped = StyleCarry(both.source, both.mean, np.ascontiguousarray(both.damping), both.radius)
    return {s: StyleCarry(*(a[k : k + 1] for a in damped.arrays)) for k, s in enumerate(styles)}


def main(argv: list[str]) -> None:
    from .model import WEIGHTS_DIR, LTIStyleModel

    folder = Path(argv[0]) if argv else WEIGHTS_DIR
    model = LTIStyleModel(weights_dir=folder, raised_arms=False)
    print(save(fit(model), folder))


if __name__ == "__main__":
    main(sys.argv[1:])
