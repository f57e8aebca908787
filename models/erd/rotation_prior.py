"""The fits of Style-ERD's rotation priors (`slow_carry.SlowPrior`, `models.motion.style_carry`)
from real TRAIN clips, the same way for every style (`python -m models.erd fit`):

1. **Leaves** (`leaf_prior.npz`): the position-trained network never learned bone twists or the
   head, hands and toes, so those come from the input, first carried from the real neutral
   distribution to the real target style's.
2. **Output** (`output_prior.npz`): the network's rotations, carried from what it produces toward
   each style (streamed over TRAIN neutral clips) to the style's real distribution and clamped
   into its range. The legs are only clamped (the foot planter re-poses them; carried, they
   turned straight walks).
3. **Runs** (`*_prior_run.npz`): both fitted again on running clips alone (each style's own
   speed split, `models.motion.gait_split`), for frames where the input runs (`gait.py`); the run
   output prior carries the legs too.
The Root is left alone, the Hips by the leaf prior; the output prior reads the Hips without
their heading and only clamps them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..motion.bn_skeleton import HIPS, NUM_JOINTS, ROOT
from ..motion.feet import LEG_JOINTS
from ..motion.gait_split import running, split_by_gait
from ..motion.rotation_ball import comparable
from ..motion.style_carry import StyleCarry
from .dataset import STYLES, TARGET_STYLES
from .slow_carry import SlowPrior

LEAF_FILE = "leaf_prior.npz"  # each with its run prior beside it (`slow_carry.run_file`)
OUTPUT_FILE = "output_prior.npz"
FIXED = (ROOT, HIPS)  # joint_Root and Hips: their rotation holds the heading
FIT_CLIPS_PER_CONTENT = 4
RUN_FIT_CLIPS = 12  # TRAIN neutral clips that run, for the run output prior
FIT_FRAMES = 240
RUN_ARMS = tuple(f"{j}_{s}" for s in "LR" for j in ("Shoulder", "UpperArm", "LowerArm", "Hand"))  # `fit_output`


def real_rotations(runs: bool = False) -> list[np.ndarray]:
    """Per style (dataset order, neutral first): local rotations (N, 22, 4) of every TRAIN frame
    (with `runs`: of the clips that run, by the style's own split of its clips' median Hips
    speeds, `models.motion.gait_split`), from the feature cache (`dataset.py`; joint_Root static,
    left at the identity)."""
    from .dataset import load_split
    from .features import NB, ROOTVEL, ROT

    split = load_split("train")
    frame_style = np.repeat(split.style, split.lengths)
    wanted: np.ndarray | bool = True
    if runs:
        speed = np.hypot(split.feats[:, ROOTVEL][:, 0], split.feats[:, ROOTVEL][:, 2])
        median = np.array([np.median(speed[a : a + n]) for a, n in zip(split.starts, split.lengths)])
        runs_clip = np.zeros(len(median), bool)
        for s in range(len(STYLES)):
            runs_clip[split.style == s] = running(median[split.style == s])
        wanted = np.repeat(runs_clip, split.lengths)
    out = []
    for s in range(len(STYLES)):
        body = split.feats[(frame_style == s) & wanted][:, ROT].reshape(-1, NB, 4).astype(np.float64)
        q = np.zeros((len(body), NUM_JOINTS, 4))
        q[..., 3] = 1.0
        q[:, 1:] = body
        out.append(q)
    return out


def fit_leaf(model: Any, styles: list[str] | None = None) -> SlowPrior:
    """Real neutral -> each of `styles`' (default: every target style) real frames, and the same on
    runs alone."""
    styles = styles or list(TARGET_STYLES)

    def fitted(real: list[np.ndarray]) -> StyleCarry:
        return StyleCarry.fit([real[0]] * len(styles), [real[STYLES.index(s)] for s in styles], FIXED)

    return SlowPrior(tuple(styles), fitted(real_rotations()), fitted(real_rotations(runs=True)))


def _neutral_inputs() -> list:
    """The first `FIT_FRAMES` of `FIT_CLIPS_PER_CONTENT` TRAIN neutral clips of every content."""
    from ..data import load_motions
    from ..eval.run import pick_clips

    return [m.slice(0, FIT_FRAMES) for m in load_motions(pick_clips(FIT_CLIPS_PER_CONTENT, split="train"))]


def _running_inputs() -> list:
    """The first `FIT_FRAMES` of the first `RUN_FIT_CLIPS` TRAIN neutral clips (by name) that run
    (`models.motion.gait_split`)."""
    from ..data import build_index, load_motions, select
    from ..eval.run import INPUT_STYLE
    from .dataset import DATASET

    clips = sorted(select(build_index([DATASET]), split="train", style=INPUT_STYLE), key=lambda c: c.name)
    _, runs = split_by_gait(load_motions(clips))
    return [m.slice(0, FIT_FRAMES) for m in runs[:RUN_FIT_CLIPS]]


def fit_output(model: Any, styles: list[str] | None = None) -> SlowPrior:
    """The model's outputs (its leaf prior in place, no output prior) over TRAIN neutral clips
    toward each of `styles` (default: every target style) -> the real style, the legs only
    clamped. The run prior: TRAIN neutral clips that run, against the real runs, the legs carried
    too; the arms (`RUN_ARMS`) as the stream makes them and every other joint with the input's own
    twists and leaves (with the leaf prior, heads jumped as a stream started mid-run)."""
    styles = styles or list(TARGET_STYLES)
    legs = tuple(model.skeleton.index(n) for n in LEG_JOINTS)

    def fitted(produced: list[np.ndarray], real: list[np.ndarray], clamped: tuple[int, ...]) -> StyleCarry:
        targets = [comparable(real[STYLES.index(s)]) for s in styles]
        return StyleCarry.fit(produced, targets, (0,), clamp_only=clamped)

    walk = fitted(network_rotations(model, _neutral_inputs(), styles=styles), real_rotations(), (HIPS,) + legs)
    run = fitted(run_network_rotations(model, styles), real_rotations(runs=True), (HIPS,))
    return SlowPrior(tuple(styles), walk, run, HIPS)


def run_network_rotations(model: Any, styles: Sequence[str] | None = None) -> list[np.ndarray]:
    """`network_rotations` of TRAIN neutral clips that run: the arms (`RUN_ARMS`) as the stream
    makes them, every other joint with the input's own twists and leaves (no leaf prior)."""
    inputs = _running_inputs()
    produced = network_rotations(model, inputs, leaf_prior=False, styles=styles)
    arms = [model.skeleton.index(n) for n in RUN_ARMS]
    for own, leafed in zip(produced, network_rotations(model, inputs, styles=styles)):
        own[:, arms] = leafed[:, arms]
    return produced


def network_rotations(
    model: Any, inputs: list, leaf_prior: bool = True, styles: Sequence[str] | None = None
) -> list[np.ndarray]:
    """Per style of `styles` (default: the model's): the rotations (N, J, 4, the Hips without
    their heading) of every frame of `inputs` streamed toward it by the network, with its leaf
    prior (not its run prior) where `leaf_prior`, and no output prior or twist range (what the
    output priors carry from)."""
    from ..eval.run import stylise

    saved = model.stages
    leaf = saved.leaf_prior
    leaf = replace(leaf, run=None) if leaf_prior and isinstance(leaf, SlowPrior) else None
    model.stages = saved.replace(leaf_prior=leaf, output_prior=None, twist_range=None)
    try:
        ks = [model.styles().index(s) for s in styles or model.styles()]
        outs = stylise(model, [m for _ in ks for m in inputs], [k for k in ks for _ in inputs])
    finally:
        model.stages = saved
    n = len(inputs)
    return [comparable(np.concatenate([o.rotations for o in outs[i * n : (i + 1) * n]])) for i in range(len(ks))]
