"""The rotation priors of the streaming Style-ERD, fitted from real TRAIN clips
(`models.motion.style_carry.StyleCarry`) the same way for every style:

    .venv/bin/python -m models.erd.rotation_prior        # all -> models/weights/erd/*_prior*.npz
    .venv/bin/python -m models.erd.rotation_prior runs   # the run priors alone
    .venv/bin/python -m models.erd.rotation_prior twists # the arms' twist range alone (`twist_range.py`)
    .venv/bin/python -m models.erd.rotation_prior hinges # the decoding's hinge joints (`models.motion.hinge`)
    .venv/bin/python -m models.erd.rotation_prior sources # what uploads' stages carry from (`upload_stages.py`)

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

import sys
from pathlib import Path

import numpy as np

from ..motion.bn_skeleton import HIPS, NUM_JOINTS, ROOT
from ..motion.feet import LEG_JOINTS
from ..motion.gait_split import running, split_by_gait
from ..motion.rotation_ball import comparable
from ..motion.style_carry import StyleCarry

LEAF_FILE = "leaf_prior.npz"
OUTPUT_FILE = "output_prior.npz"
RUN_LEAF_FILE = "leaf_prior_run.npz"
RUN_OUTPUT_FILE = "output_prior_run.npz"
PRIOR_FILES = {  # `stages.ErdStages`' prior fields and their files beside the weights
    "leaf_prior": LEAF_FILE,
    "output_prior": OUTPUT_FILE,
    "run_leaf_prior": RUN_LEAF_FILE,
    "run_output_prior": RUN_OUTPUT_FILE,
}
FIXED = (ROOT, HIPS)  # joint_Root and Hips: their rotation holds the heading
FIT_CLIPS_PER_CONTENT = 4
RUN_FIT_CLIPS = 12  # TRAIN neutral clips that run, for the run output prior
FIT_FRAMES = 240
RUN_ARMS = tuple(f"{j}_{s}" for s in "LR" for j in ("Shoulder", "UpperArm", "LowerArm", "Hand"))  # `fit_output_prior`


def real_rotations(runs: bool = False) -> list[np.ndarray]:
    """Per style (dataset order, neutral first): local rotations (N, 22, 4) of every TRAIN frame
    (with `runs`: of the clips that run, by the style's own split of its clips' median Hips
    speeds, `models.motion.gait_split`), from the feature cache (`dataset.py`; joint_Root static,
    left at the identity)."""
    from .dataset import STYLES, load_split
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


def fit_leaf_prior(real: list[np.ndarray]) -> StyleCarry:
    """Real neutral -> real target style, for each target style."""
    return StyleCarry.fit([real[0]] * (len(real) - 1), real[1:], FIXED)


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


def fit_output_prior(model, real: list[np.ndarray], runs: bool = False) -> StyleCarry:
    """The model's outputs (its leaf prior in place, no output prior) over TRAIN neutral clips
    toward each style -> the real style. With `runs`: TRAIN neutral clips that run, against the
    real runs, the legs carried too; the arms (`RUN_ARMS`) as the stream makes them and every other
    joint with the input's own twists and leaves (with the leaf prior, heads jumped as a stream
    started mid-run)."""
    produced = run_network_rotations(model) if runs else network_rotations(model, _neutral_inputs())
    clamped = (HIPS,) + (() if runs else tuple(model.skeleton.index(n) for n in LEG_JOINTS))
    return StyleCarry.fit(produced, [comparable(q) for q in real[1:]], (0,), clamp_only=clamped)


def run_network_rotations(model) -> list[np.ndarray]:
    """`network_rotations` of TRAIN neutral clips that run: the arms (`RUN_ARMS`) as the stream
    makes them, every other joint with the input's own twists and leaves (no leaf prior)."""
    inputs = _running_inputs()
    produced = network_rotations(model, inputs, leaf_prior=False)
    arms = [model.skeleton.index(n) for n in RUN_ARMS]
    for own, leafed in zip(produced, network_rotations(model, inputs)):
        own[:, arms] = leafed[:, arms]
    return produced


def network_rotations(model, inputs: list, leaf_prior: bool = True) -> list[np.ndarray]:
    """Per target style: the rotations (N, J, 4, the Hips without their heading) of every frame
    of `inputs` streamed toward it by the network, with its leaf prior where `leaf_prior`, and
    no output priors or twist range (what the output priors carry from)."""
    from ..eval.run import stylise

    saved = model.stages
    off = ("output_prior", "run_leaf_prior", "run_output_prior", "twist_range")
    model.stages = saved.without(*off) if leaf_prior else saved.without("leaf_prior", *off)
    try:
        styles = model.styles()
        outs = stylise(model, [m for _ in styles for m in inputs], [k for k in range(len(styles)) for _ in inputs])
    finally:
        model.stages = saved
    n = len(inputs)
    return [comparable(np.concatenate([o.rotations for o in outs[k * n : (k + 1) * n]])) for k in range(len(styles))]


def main(argv: list[str]) -> None:
    import torch

    from ..settings import get_settings
    from .runtime import load

    torch.set_num_threads(1)
    what = argv[0] if argv else "all"  # the hinges first: the output priors carry from the decoded pose
    folder = Path(argv[1]) if len(argv) > 1 else get_settings().weights_dir / "erd"
    if what in ("all", "hinges"):
        from ..motion.assets import bandai_namco_skeleton
        from ..motion.hinge import HINGE_FILE
        from .dataset import load_split, split_hinges

        print(split_hinges(load_split("train"), bandai_namco_skeleton()).save(folder / HINGE_FILE))
    if what in ("all", "leaves", "output"):
        real = real_rotations()
        if what in ("all", "leaves"):
            print(fit_leaf_prior(real).save(folder / LEAF_FILE))
        if what in ("all", "output"):
            print(fit_output_prior(load(folder), real).save(folder / OUTPUT_FILE))
    if what in ("all", "twists"):
        from .twist_range import TWIST_FILE, TwistRange

        print(TwistRange.fit(load(folder).skeleton, real_rotations()[1:]).save(folder / TWIST_FILE))
    if what in ("all", "runs"):
        real = real_rotations(runs=True)
        print(fit_leaf_prior(real).save(folder / RUN_LEAF_FILE))
        print(fit_output_prior(load(folder), real, runs=True).save(folder / RUN_OUTPUT_FILE))
    if what in ("all", "sources"):
        from .upload_stages import SOURCES_FILE, fit_sources

        print(fit_sources(load(folder)).save(folder / SOURCES_FILE))


if __name__ == "__main__":
    main(sys.argv[1:])
