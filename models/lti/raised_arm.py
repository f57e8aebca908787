"""A raised hand that does not wave: its arm carried toward how the real style holds a raised arm.

    .venv/bin/python -m models.lti.raised_arm      # fit every style -> models/weights/lti/raised_arm.npz

The translators are linear maps fitted over every content, walks most of all; a raised arm lies
far from that. Per style and side, a `StyleCarry` from the translator's rotations of neutral TRAIN
clips to the style's real TRAIN clips, both on frames where that hand is raised and calm
(`models.motion.hands.calm_frames`), gains capped at 1 so the sway is not magnified. While the
input's hand is raised and calm, that arm is mixed toward the carried one (`kernels.carry_raised_arms`).
Uploads get the same fit from their clip (`fit_upload`).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..motion.bn_skeleton import BN_JOINTS, HIPS, NUM_JOINTS, ROOT
from ..motion.feet import LEG_JOINTS
from ..motion.hands import RAISE_RAMP_CM, WAVE_RAMP_CM_S, calm_frames, calm_sides
from ..motion.rotation_ball import comparable
from ..motion.style_carry import StyleCarry
from .kernels import RaisedArm

if TYPE_CHECKING:
    from ..motion.skeleton import Motion
    from .model import LTIStyleModel, StyleTranslator

FILE = "raised_arm.npz"
ARM_JOINTS = ("Shoulder", "UpperArm", "LowerArm", "Hand")
FIT_FRAMES = 240
MIN_CALM_FRAMES = 15  # a side whose real clips hold fewer raised, calm frames is not fitted
_ARM = [np.array([BN_JOINTS.index(f"{j}_{side}") for j in ARM_JOINTS]) for side in "LR"]


def settings(carries: list[StyleCarry | None], keep: float) -> RaisedArm:
    """The compiled step's `kernels.RaisedArm` for the styles' carries (None: none), eased by `keep`."""
    fitted = [c for c in carries if c is not None]
    none = (np.zeros((0, NUM_JOINTS, *shape)) for shape in ((4,), (4,), (3, 3), ()))  # no style has one
    both = StyleCarry.stack(fitted) if fitted else StyleCarry(*none)
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
        float(keep),
    )


def load(folder: Path) -> dict[str, StyleCarry]:
    """Per style, its one-style carry from `folder`/`FILE` (none when the file is missing)."""
    path = Path(folder) / FILE
    if not path.exists():
        return {}
    with np.load(path) as z:
        styles, both = [str(s) for s in z["styles"]], StyleCarry.read(z)
    return {s: StyleCarry(*(a[k : k + 1] for a in both.arrays)) for k, s in enumerate(styles)}


def save(carries: dict[str, StyleCarry], folder: Path) -> Path:
    path = Path(folder) / FILE
    both = StyleCarry.stack(list(carries.values()))
    np.savez(path, styles=np.array(list(carries)), source=both.source, mean=both.mean, map=both.map, radius=both.radius)
    return path


def fit(model: LTIStyleModel) -> dict[str, StyleCarry | None]:
    """Per style of the model (raised arms off): the carry above, from all its TRAIN clips."""
    from ..data import build_index, load_motions, select
    from ..eval.run import DATASET, INPUT_STYLE

    train = select(build_index([DATASET]), split="train")
    inputs = [m.slice(0, FIT_FRAMES) for m in load_motions([c for c in train if c.style == INPUT_STYLE])]
    real = {s: load_motions([c for c in train if c.style == s]) for s in model.styles()}
    return fit_styles(model, real, inputs)


def fit_styles(model: LTIStyleModel, real: dict, inputs: list) -> dict[str, StyleCarry | None]:
    """Per style with real clips in `real`: the carry per side on calm raised frames (None: neither)."""
    from ..eval.run import stylise

    targets = {s: [_real_frames(real[s], side) for side in (0, 1)] for s in real}
    styles = [s for s in real if any(len(t) >= MIN_CALM_FRAMES for t in targets[s])]
    if not styles:  # no raised, calm hand anywhere (most uploads): nothing to stylise or fit
        return dict.fromkeys(real)
    # inputs without a raised, calm hand add nothing; the first stays as a stand-in
    calm = [calm_sides(m) for m in inputs]
    kept_inputs = [k for k, c in enumerate(calm) if k == 0 or c.any()]
    inputs = [inputs[k] for k in kept_inputs]
    rows = [model.styles().index(s) for s in styles]
    outs = stylise(model, [m for _ in styles for m in inputs], [k for k in rows for _ in inputs])
    n = len(inputs)
    made = [comparable(np.concatenate([o.rotations for o in outs[k * n : (k + 1) * n]])) for k in range(len(styles))]
    clamped = (HIPS,) + tuple(BN_JOINTS.index(j) for j in LEG_JOINTS)
    chosen = [np.concatenate([calm[k][:, side] for k in kept_inputs]) for side in (0, 1)]
    carries: dict[str, StyleCarry | None] = dict.fromkeys(real)
    for k, style in enumerate(styles):
        sides, fitted = [], []
        for side in (0, 1):
            target = targets[style][side]
            fitted.append(len(target) >= MIN_CALM_FRAMES)
            kept = (ROOT,) if fitted[-1] else (ROOT, *_ARM[side])  # an unfitted arm is left as it is
            target = target if fitted[-1] else made[k][:1]
            sides.append(StyleCarry.fit([made[k][chosen[side]]], [target], kept, clamp_only=clamped))
        both = sides[0].with_maps_of(sides[1], [0], list(_ARM[1]))
        carries[style] = StyleCarry(both.source, both.mean, np.ascontiguousarray(both.damping), both.radius)
    return carries


def fit_upload(translator: StyleTranslator, clip: Motion, ref: np.ndarray) -> StyleCarry | None:
    """An uploaded style's carry from its clip; None without a raised, calm hand."""
    from .finetune import neutral_bank
    from .model import LTIStyleModel

    bank = neutral_bank(np.ascontiguousarray(ref, dtype=np.float64).tobytes())
    inputs = [m.slice(0, FIT_FRAMES) for m in bank.motions.values()]
    model = LTIStyleModel({translator.style: translator}, off=("raised_arm",))
    return fit_styles(model, {translator.style: [clip]}, inputs)[translator.style]


def _real_frames(motions: list, side: int) -> np.ndarray:
    """(N, J, 4) `comparable` rotations of the frames with the `side` hand raised and calm."""
    if not motions:
        return np.zeros((0, NUM_JOINTS, 4))
    q = np.concatenate([m.rotations[calm_frames(m, side)] for m in motions]).astype(np.float64)
    q[:, ROOT] = (0.0, 0.0, 0.0, 1.0)
    return comparable(q)


def main(argv: list[str]) -> None:
    import argparse

    from .model import WEIGHTS_DIR, LTIStyleModel

    parser = argparse.ArgumentParser(prog="python -m models.lti.raised_arm", description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, nargs="?", default=WEIGHTS_DIR, help="the LTI weights to fit and write")
    folder = parser.parse_args(argv).folder
    model = LTIStyleModel(weights_dir=folder, off=("raised_arm",))
    carries = fit(model)
    print(save({s: c for s, c in carries.items() if c is not None}, folder))


if __name__ == "__main__":
    main(sys.argv[1:])
