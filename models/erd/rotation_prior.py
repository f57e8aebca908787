"""The rotation prior of the streaming Style-ERD, fitted from real TRAIN clips (`carry.StyleCarry`):

    .venv/bin/python -m models.erd.rotation_prior        # all -> models/weights/erd/{leaf,output}_prior{,_run}.npz
    .venv/bin/python -m models.erd.rotation_prior runs   # the run priors alone
    .venv/bin/python -m models.erd.rotation_prior twists # the arms' twist range alone (`twist_range.py`)
    .venv/bin/python -m models.erd.rotation_prior gestures  # a raised hand's output priors alone (`gestures.py`)

1. **Twists and leaves** (`leaf_prior.npz`). The decoder is trusted only for where bones point
   (`models.motion.twist.transfer_twist`): a bone's twist about itself and the head, hands and
   toes move no joint, so the position-trained network never learned them. Copied from the
   neutral input they stayed neutral on every output (the rotation judge recognised 9-29 % of
   the styles, and neutral hands left the feminine or exhausted style's real range in 15-20 % of
   frames). So the input's rotations are first carried from the real neutral distribution to the
   real target style's, and the twists and leaves are taken from that.
2. **The output** (`output_prior.npz`). The network's own bone directions, trained against a
   discriminator on positions, are recognisable to a position judge, but their rotations are not
   the style's: shoulders and spine too square or too still, arm swings with the wrong spread.
   The output rotations (after 1.) are carried from the distribution the network produces toward
   each style (measured by running it over TRAIN neutral clips) to the style's real one, and
   clamped into the style's real range. This moves joints: the foot planter runs after it. The
   legs are only clamped: the planter re-poses them anyway, and carrying their rotations as
   well made the content judge read straight validation walks as turns (content 0.70-0.90
   per style against 0.79-0.97 with the legs only clamped).

3. **Runs** (`leaf_prior_run.npz`, `output_prior_run.npz`): both fitted again on runs alone (the
   real neutral and style runs; the network driven by TRAIN neutral runs), for the frames where
   the input runs (`gait.py`: the share ramps with the input's Hips speed). Fitted over every
   content, the priors carried runs toward walks and gestures. The run output prior carries the
   legs too: only clamped, the runs' legs stayed the network's near-neutral stride, and the
   position judge read 2 of the 4 validation runs toward elderly and toward exhausted as normal
   (a walk, below the ramp, never takes it, so no straight walk turns).

The Root is left alone by both, the Hips by the leaf prior (the decoder's legs and spine fix
them). The output prior reads the Hips without their heading (their twist about world up, as the
eval suite compares them) and only clamps them: the rest of the body hangs from them.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..motion.bn_skeleton import HIPS, NUM_JOINTS, ROOT
from ..motion.feet import LEG_JOINTS
from ..motion.hands import hanging_frames, raised_frames
from ..motion.rotation_ball import comparable, split_heading
from ..motion.rotations import quat_mul
from ..motion.style_carry import StyleCarry, real_train_frames

LEAF_FILE = "leaf_prior.npz"
OUTPUT_FILE = "output_prior.npz"
RUN_LEAF_FILE = "leaf_prior_run.npz"
RUN_OUTPUT_FILE = "output_prior_run.npz"
GESTURE_FILE = "output_prior_gesture.npz"
RAISE_FILE = "output_prior_raise.npz"
HANGING_FILE = "output_prior_hanging.npz"
PRIOR_FILES = {  # `runtime.ERDModel`'s prior attributes and their files beside the weights
    "leaf_prior": LEAF_FILE,
    "output_prior": OUTPUT_FILE,
    "run_leaf_prior": RUN_LEAF_FILE,
    "run_output_prior": RUN_OUTPUT_FILE,
    "gesture_prior": GESTURE_FILE,
    "raise_prior": RAISE_FILE,
    "hanging_prior": HANGING_FILE,
}
FIXED = (ROOT, HIPS)  # joint_Root and Hips: their rotation holds the heading
FIT_CLIPS_PER_CONTENT = 4
RUN_FIT_CLIPS = 12  # TRAIN neutral runs for the run output prior: 4, as per content above, would be 960 frames
ARMS = tuple(f"{j}_{s}" for s in "LR" for j in ("Shoulder", "UpperArm", "LowerArm", "Hand"))
# per style, the joints whose run output prior is fitted with the run leaf prior in place (None: every joint)
RUN_SOURCE_WITH_LEAF: dict[str, tuple[str, ...] | None] = {"feminine": ARMS, "active": None}
FIT_FRAMES = 240


def real_rotations(runs: bool = False) -> list[np.ndarray]:
    """Per style (dataset order, neutral first): local rotations (N, 22, 4) of every TRAIN frame
    (with `runs`: of the runs only), from the feature cache (`dataset.py`; joint_Root static,
    left at the identity)."""
    from .dataset import CONTENTS, STYLES, load_split
    from .features import NB, ROT

    split = load_split("train")
    frame_style = np.repeat(split.style, split.lengths)
    wanted = np.repeat(split.content == CONTENTS.index("run"), split.lengths) if runs else True
    out = []
    for s in range(len(STYLES)):
        body = split.feats[(frame_style == s) & wanted][:, ROT].reshape(-1, NB, 4).astype(np.float64)
        q = np.zeros((len(body), NUM_JOINTS, 4))
        q[..., 3] = 1.0
        q[:, 1:] = body
        out.append(q)
    return out


def carry_output_numpy(prior: StyleCarry, rot: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The numpy reference of the output prior on rotations (B, J, 4), the Hips carried without
    their heading: what `prior(rot, weights, hips=HIPS)` computes compiled."""
    heading, free = split_heading(rot)
    out = prior.apply_numpy(free, weights)
    out[:, HIPS] = quat_mul(heading, out[:, HIPS])
    return out


def fit_leaf_prior(real: list[np.ndarray]) -> StyleCarry:
    """Real neutral -> real target style, for each of the 6 target styles."""
    return StyleCarry.fit([real[0]] * (len(real) - 1), real[1:], FIXED)


def fit_output_prior(model, real: list[np.ndarray], runs: bool = False) -> StyleCarry:
    """The model's outputs (its leaf prior in place, no output prior) over TRAIN neutral clips
    toward each style -> the real style. With `runs`: TRAIN neutral runs with the input's own
    twists and leaves (no leaf prior: chosen on validation over the run leaf prior in place,
    model card), except the joints `RUN_SOURCE_WITH_LEAF` names, taken as the stream carries them
    (the leaf prior in place: without it feminine's arm source means sat 29-66 degrees from what
    the stream makes of the validation runs; feminine's head and spine keep the first source,
    whose change made the head jump as a stream starts mid-run, model card), against the real
    runs in `real`; the legs carried as well, not only clamped (module docstring)."""
    from ..data import load_motions
    from ..eval.run import pick_clips

    clips = (
        pick_clips(RUN_FIT_CLIPS, ("run",), split="train") if runs else pick_clips(FIT_CLIPS_PER_CONTENT, split="train")
    )
    inputs = [m.slice(0, FIT_FRAMES) for m in load_motions(clips)]
    produced = network_rotations(model, inputs, leaf_prior=not runs)
    if runs:  # these styles' joints as the stream makes them, the run leaf prior in place
        leafed = network_rotations(model, inputs, leaf_prior=True)
        for k, style in enumerate(model.styles()):
            if style in RUN_SOURCE_WITH_LEAF:
                names = RUN_SOURCE_WITH_LEAF[style] or model.skeleton.names
                joints = [model.skeleton.index(n) for n in names]
                produced[k][:, joints] = leafed[k][:, joints]
    clamped = (HIPS,) + (() if runs else tuple(model.skeleton.index(n) for n in LEG_JOINTS))
    return StyleCarry.fit(produced, [comparable(q) for q in real[1:]], (0,), clamp_only=clamped)


def network_rotations(model, inputs: list, leaf_prior: bool = True) -> list[np.ndarray]:
    """Per target style: the rotations (N, J, 4, the Hips without their heading) of every frame
    of `inputs` streamed toward it by the network, with its leaf prior where `leaf_prior`, and
    no output priors or twist range (what the output priors carry from)."""
    from ..eval.run import stylise

    saved = model.leaf_prior, model.output_prior, model.run_leaf_prior, model.run_output_prior, model.twist_range
    gesture = model.gesture_prior
    if not leaf_prior:
        model.leaf_prior = None
    model.output_prior = model.run_leaf_prior = model.run_output_prior = model.twist_range = model.gesture_prior = None
    try:
        styles = model.styles()
        outs = stylise(model, [m for _ in styles for m in inputs], [k for k in range(len(styles)) for _ in inputs])
    finally:
        model.leaf_prior, model.output_prior, model.run_leaf_prior, model.run_output_prior, model.twist_range = saved
        model.gesture_prior = gesture
    n = len(inputs)
    return [comparable(np.concatenate([o.rotations for o in outs[k * n : (k + 1) * n]])) for k in range(len(styles))]


def _fit_on_frames(model, contents: tuple[str, ...], frames: Callable) -> StyleCarry:
    """An output prior on chosen frames (`frames(motion)` -> (T,) bool): the network (its leaf
    prior in place, no output prior) over the first `FIT_FRAMES` of `FIT_CLIPS_PER_CONTENT`
    TRAIN neutral clips of each of `contents`, toward each style, against every real TRAIN clip
    of those contents in the style; the legs and Hips only clamped, as the all-content prior."""
    from ..data import load_motions
    from ..eval.run import pick_clips

    inputs = [m.slice(0, FIT_FRAMES) for m in load_motions(pick_clips(FIT_CLIPS_PER_CONTENT, contents, split="train"))]
    chosen = np.concatenate([frames(m) for m in inputs])
    produced = [q[chosen] for q in network_rotations(model, inputs)]
    real = real_train_frames(model.styles(), contents, frames)
    clamped = (HIPS,) + tuple(model.skeleton.index(n) for n in LEG_JOINTS)
    return StyleCarry.fit(produced, real, (ROOT,), clamp_only=clamped)


def _merged(base: StyleCarry, parts: list[tuple[StyleCarry, list[int]]], styles: tuple[str, ...], names: list[str]):
    """`base` with the rows of `styles` (of the model's `names`) replaced, joint by joint, by the
    `parts` (a carry and the joints taken from it); every other style keeps `base`'s maps, so a
    mix with them carries them as before (each joint's map is fitted on its own)."""
    rows = [names.index(s) for s in styles]
    for part, joints in parts:
        base = base.with_maps_of(part, rows, joints)
    return base


def fit_gesture_prior(model) -> StyleCarry:
    """The output prior of a waving hand (`gestures.py`): fitted on every raise-up and wave
    content, on the frames with a hand raised (`_fit_on_frames`), for `gestures.GESTURE_STYLES`;
    the other styles keep the all-content prior's maps."""
    from .dataset import CONTENTS
    from .gestures import GESTURE_STYLES

    gestures = tuple(c for c in CONTENTS if c.startswith(("raise-up", "wave")))
    fitted = _fit_on_frames(model, gestures, raised_frames)
    every = list(range(NUM_JOINTS))
    return _merged(model.output_prior, [(fitted, every)], GESTURE_STYLES, list(model.styles()))


def fit_raise_prior(model) -> StyleCarry:
    """The output prior of a hand raised and held still (`gestures.py`): for each side, fitted on
    the raise-up contents on the frames with that side's hand raised, and that side's arm
    (`gestures.ARM_JOINTS`) taken from its own fit, for `gestures.RAISED_STYLES`. Fitted on
    either hand at once, a joint's one Gaussian had to hold the raised arm and the hanging one
    of a raise-up with the other hand (validation: right-hand raise-ups toward active lost
    content margin instead of gaining it, model card). Every other joint and style keeps the
    all-content prior's maps."""
    from .dataset import CONTENTS
    from .gestures import ARM_JOINTS, RAISED_STYLES

    raise_ups = tuple(c for c in CONTENTS if c.startswith("raise-up"))
    parts = [
        (
            _fit_on_frames(model, raise_ups, functools.partial(raised_frames, side=side)),
            [model.skeleton.index(f"{j}_{s}") for j in ARM_JOINTS],
        )
        for side, s in enumerate("LR")
    ]
    return _merged(model.output_prior, parts, RAISED_STYLES, list(model.styles()))


def fit_hanging_prior(model) -> StyleCarry:
    """The output prior of the arm that hangs while the other hand is raised (`gestures.py`): for
    each of `gestures.HANGING_SIDES`, fitted on the one-hand raise-ups and waves on the frames
    with that arm down and the other hand raised, that side's arm taken from its fit, for
    `gestures.RAISED_STYLES`. The all-content prior carried the hanging arm by maps fitted mostly
    on swinging arms; the real one hangs within a few degrees (active: 3-10 degrees of spread in
    the upper arm). Every other joint and style keeps the all-content prior's maps."""
    from .dataset import CONTENTS
    from .gestures import ARM_JOINTS, HANGING_SIDES, RAISED_STYLES

    one_hand = tuple(c for c in CONTENTS if c.startswith(("raise-up", "wave")) and "both" not in c)
    parts = [
        (
            _fit_on_frames(model, one_hand, functools.partial(hanging_frames, side="LR".index(s))),
            [model.skeleton.index(f"{j}_{s}") for j in ARM_JOINTS],
        )
        for s in HANGING_SIDES
    ]
    return _merged(model.output_prior, parts, RAISED_STYLES, list(model.styles()))


def main(argv: list[str]) -> None:
    import torch

    from ..settings import get_settings
    from .runtime import load

    torch.set_num_threads(1)
    what = argv[0] if argv else "both"
    folder = Path(argv[1]) if len(argv) > 1 else get_settings().weights_dir / "erd"
    if what in ("both", "leaves", "output"):
        real = real_rotations()
        if what in ("both", "leaves"):
            print(fit_leaf_prior(real).save(folder / LEAF_FILE))
        if what in ("both", "output"):
            print(fit_output_prior(load(folder), real).save(folder / OUTPUT_FILE))
    if what in ("both", "twists"):
        from .twist_range import TWIST_FILE, TwistRange

        print(TwistRange.fit(load(folder).skeleton, real_rotations()[1:]).save(folder / TWIST_FILE))
    if what in ("both", "runs"):
        real = real_rotations(runs=True)
        print(fit_leaf_prior(real).save(folder / RUN_LEAF_FILE))
        print(fit_output_prior(load(folder), real, runs=True).save(folder / RUN_OUTPUT_FILE))
    if what in ("both", "gestures"):  # after the output prior: the other styles keep its maps
        print(fit_gesture_prior(load(folder)).save(folder / GESTURE_FILE))
        print(fit_raise_prior(load(folder)).save(folder / RAISE_FILE))
        print(fit_hanging_prior(load(folder)).save(folder / HANGING_FILE))


if __name__ == "__main__":
    main(sys.argv[1:])
