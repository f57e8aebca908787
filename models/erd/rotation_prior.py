"""The fits of Style-ERD's rotation priors (`slow_carry.SlowPrior`, `models.motion.style_carry`)
from real TRAIN clips, the same way for every style (`python -m models.erd fit`):

1. **Leaves** (`leaf_prior.npz`): the position-trained network never learned bone twists or the
   head, hands and toes, so those come from the input, carried from real neutral to the style.
2. **Output** (`output_prior.npz`): the network's rotations carried toward each style's real
   distribution and clamped into its range; legs only clamped (the foot planter re-poses them).
   Each other joint takes the whole carry, its mean shift or the clamp alone, whichever lands
   nearest the real frames (`output_carry`).
3. **Runs** (`*_prior_run.npz`): both fitted again on running clips, for frames that run; the
   output prior also on standing clips (`*_prior_stand.npz`), for frames that stand (`gait.py`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..motion.bn_skeleton import HIPS, NUM_JOINTS, ROOT
from ..motion.feet import LEGS
from ..motion.gait_split import MOVING_CM_S, clip_speed, running, split_by_gait
from ..motion.rotation_ball import comparable
from ..motion.rotations import quat_exp, quat_inv, quat_log, quat_mul
from ..motion.style_carry import StyleCarry
from .dataset import STYLES, TARGET_STYLES
from .slow_carry import SlowPrior

LEAF_FILE = "leaf_prior.npz"  # each with its gaits' priors beside it (`slow_carry.gait_file`)
OUTPUT_FILE = "output_prior.npz"
FIXED = (ROOT, HIPS)  # joint_Root and Hips: their rotation holds the heading
FIT_CLIPS_PER_CONTENT = 12  # TRAIN neutral clips per content the network's output spread is estimated from (validation)
RUN_FIT_CLIPS = 12  # TRAIN neutral clips that run, for the run output prior
FIT_FRAMES = 240
PER_CONTENT = 2000  # frames each content weighs in a fitted prior, its inputs and the style's real frames alike
SUPPORT_FRAMES = 40_000  # real frames per style `nearest_real` measures against (evenly spread)
NEAR_PERCENTILE = 95.0  # of the distances to the nearest real frame `output_carry` compares
NEAR_MARGIN_DEG = 1.0  # how much nearer a lesser carry must bring them to replace the whole (validation)
# the share of the way to the style's rotations each carry goes (docs/eval/ablation.md)
CARRY_SHARE = 1.0
RUN_ARMS = tuple(f"{j}_{s}" for s in "LR" for j in ("Shoulder", "UpperArm", "LowerArm", "Hand"))  # `fit_output`


def content_balanced(frames: np.ndarray, contents: np.ndarray, n: int = PER_CONTENT) -> np.ndarray:
    """`frames` (N, ...) drawn again so that every content weighs `n` of them (evenly spread, repeated
    where fewer): a style's real clips and a fit's inputs mix contents differently, and a pooled
    mean would take that mix for the style."""
    picks = [np.flatnonzero(contents == c) for c in np.unique(contents)]
    return np.concatenate([frames[p[np.linspace(0, len(p) - 1, n).round().astype(int)]] for p in picks])


def real_rotations(runs: bool = False, balanced: bool = False, stands: bool = False) -> list[np.ndarray]:
    """Per style (neutral first): rotations (N, 22, 4) of every TRAIN frame (with `runs`: running
    clips; `stands`: standing clips, `gait_split`; `balanced`: `content_balanced`)."""
    from .dataset import load_split
    from .features import NB, ROOTVEL, ROT

    split = load_split("train")
    frame_style = np.repeat(split.style, split.lengths)
    wanted: np.ndarray | bool = True
    speed = np.hypot(split.feats[:, ROOTVEL][:, 0], split.feats[:, ROOTVEL][:, 2])
    median = np.array([np.median(speed[a : a + n]) for a, n in zip(split.starts, split.lengths)])
    if runs:
        runs_clip = np.zeros(len(median), bool)
        for s in range(len(STYLES)):
            runs_clip[split.style == s] = running(median[split.style == s])
        wanted = np.repeat(runs_clip, split.lengths)
    if stands:
        wanted = np.repeat(median < MOVING_CM_S, split.lengths)
    out = []
    for s in range(len(STYLES)):
        body = split.feats[(frame_style == s) & wanted][:, ROT].reshape(-1, NB, 4).astype(np.float64)
        q = np.zeros((len(body), NUM_JOINTS, 4))
        q[..., 3] = 1.0
        q[:, 1:] = body
        contents = np.repeat(split.content, split.lengths)[(frame_style == s) & wanted]
        out.append(content_balanced(q, contents) if balanced else q)
    return out


def fit_leaf(model: Any, styles: list[str] | None = None) -> SlowPrior:
    """Real neutral -> each style's real frames, and the same on runs alone."""
    styles = styles or list(TARGET_STYLES)

    def fitted(real: list[np.ndarray]) -> StyleCarry:
        return StyleCarry.fit([real[0]] * len(styles), [real[STYLES.index(s)] for s in styles], FIXED)

    walk, stood = fitted(real_rotations(balanced=True)), real_rotations(balanced=True, stands=True)
    stand = nearer(fitted(stood), walk, [comparable(stood[0])] * len(styles), _targets(stood, styles))
    return SlowPrior(tuple(styles), walk, fitted(real_rotations(runs=True)), stand=stand)


def _targets(real: list[np.ndarray], styles: Sequence[str]) -> list[np.ndarray]:
    """`real_rotations`' frames of each of `styles`, comparable (`rotation_ball.comparable`)."""
    return [comparable(real[STYLES.index(s)]) for s in styles]


def _neutral_inputs() -> tuple[list, np.ndarray]:
    """The first `FIT_FRAMES` of `FIT_CLIPS_PER_CONTENT` TRAIN neutral clips of every content, and
    each of their frames' content."""
    from ..data import load_motions
    from ..eval.run import pick_clips

    clips = pick_clips(FIT_CLIPS_PER_CONTENT, split="train")
    inputs = [m.slice(0, FIT_FRAMES) for m in load_motions(clips)]
    return inputs, np.repeat([c.content for c in clips], [m.num_frames for m in inputs])


def _running_inputs() -> list:
    """The first `FIT_FRAMES` of the first `RUN_FIT_CLIPS` TRAIN neutral clips that run."""
    from ..data import build_index, load_motions, select
    from ..eval.run import INPUT_STYLE
    from .dataset import DATASET

    clips = sorted(select(build_index([DATASET]), split="train", style=INPUT_STYLE), key=lambda c: c.name)
    _, runs = split_by_gait(load_motions(clips))
    return [m.slice(0, FIT_FRAMES) for m in runs[:RUN_FIT_CLIPS]]


def fit_output(model: Any, styles: list[str] | None = None) -> SlowPrior:
    """The model's outputs over TRAIN neutral clips -> each real style, the legs but the ankles only
    clamped; and on runs, and on standing clips. The planter bends hip joints and knees; the
    network's ankles swing several times the real spread, so they are carried like the arms."""
    styles = styles or list(TARGET_STYLES)
    legs = tuple(model.skeleton.index(chain[k]) for chain in LEGS for k in (0, 1, 3))  # hip joint, knee, toes

    inputs, contents = _neutral_inputs()
    produced = network_rotations(model, inputs, styles=styles)
    walked = [content_balanced(p, contents) for p in produced]
    walk = output_carry(walked, _targets(real_rotations(balanced=True), styles), (HIPS,) + legs)
    run = output_carry(run_network_rotations(model, styles), _targets(real_rotations(runs=True), styles), (HIPS,))
    standing = np.repeat([clip_speed(m) < MOVING_CM_S for m in inputs], [m.num_frames for m in inputs])
    stood = [content_balanced(p[standing], contents[standing]) for p in produced]
    real = _targets(real_rotations(balanced=True, stands=True), styles)
    stand = output_carry(stood, real, (), FIXED + legs)  # the legs keep the walk's clamp: a stop must not drag the feet
    return SlowPrior(tuple(styles), walk, run, HIPS, stand=nearer(stand, walk, stood, real))


def nearer(own: StyleCarry, other: StyleCarry, produced: list[np.ndarray], targets: list[np.ndarray]) -> StyleCarry:
    """`own` where it brings `produced` nearer the real `targets` than `other` by `NEAR_MARGIN_DEG`,
    else `other` (per style and joint): a gait's own fit only where it does better."""
    far = np.stack([near_percentile(k, produced, targets, own.mean) for k in (own, other)])
    far[0] -= np.radians(NEAR_MARGIN_DEG)
    return chosen((own, other), np.argmin(far, axis=0))


def output_carry(
    produced: list[np.ndarray], targets: list[np.ndarray], clamped: tuple[int, ...], fixed: tuple[int, ...] = (ROOT,)
) -> StyleCarry:
    """Per style, the carry of `produced` to real `targets`: per joint whole, mean shift or clamp,
    the nearest; `fixed` joints left alone."""
    carry = StyleCarry.fit(produced, targets, fixed, clamp_only=clamped)
    kinds = (partial(carry, CARRY_SHARE), partial(mean_shift(carry), CARRY_SHARE), carry.bounds)
    far = np.stack([near_percentile(k, produced, targets) for k in kinds])  # (3, S, J)
    far[0] -= np.radians(NEAR_MARGIN_DEG)
    return chosen(kinds, np.argmin(far, axis=0))


def mean_shift(carry: StyleCarry) -> StyleCarry:
    """`carry` without its spread: a turn from the source mean to the style's, then clamped."""
    same = np.ascontiguousarray(np.broadcast_to(np.eye(3), carry.map.shape))
    return StyleCarry(carry.source, carry.mean, same, carry.radius)


def partial(carry: StyleCarry, share: float) -> StyleCarry:
    """`carry` taken `share` of the way, the clamp still on the style's range."""
    if share == 1.0:
        return carry
    still = np.all(carry.source == carry.mean, axis=-1, keepdims=True)
    lin = np.where(still[..., None], carry.map, (1.0 - share) * np.eye(3) + share * carry.map)
    to = quat_mul(carry.source, quat_exp(share * quat_log(quat_mul(quat_inv(carry.source), carry.mean))))
    back = np.linalg.solve(lin, quat_log(quat_mul(quat_inv(carry.mean), to))[..., None])[..., 0]
    source = np.where(still, carry.source, quat_mul(carry.source, quat_exp(-back)))
    return StyleCarry(np.ascontiguousarray(source), carry.mean, np.ascontiguousarray(lin), carry.radius)


def chosen(kinds: Sequence[StyleCarry], choice: np.ndarray) -> StyleCarry:
    """One carry with (style, joint) entries from `kinds[choice[s, j]]`."""

    def pick(arrays: list[np.ndarray]) -> np.ndarray:
        at = choice.reshape(1, *choice.shape, *(1,) * (arrays[0].ndim - 2))
        return np.ascontiguousarray(np.take_along_axis(np.stack(arrays), at, 0)[0])

    return StyleCarry(*(pick([np.asarray(k.arrays[f]) for k in kinds]) for f in range(len(kinds[0].arrays))))


def nearest_real(real: np.ndarray, mean: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(N, J) rotation-vector distance about `mean` from each of `q` to the nearest of `real`."""
    from scipy.spatial import cKDTree

    real = real[np.linspace(0, len(real) - 1, min(len(real), SUPPORT_FRAMES)).astype(int)]
    pts = quat_log(quat_mul(quat_inv(mean)[None], real))
    x = quat_log(quat_mul(quat_inv(mean)[None], q))
    return np.stack([cKDTree(pts[:, j]).query(x[:, j])[0] for j in range(q.shape[1])], axis=1)


def near_percentile(
    carry: StyleCarry, produced: list[np.ndarray], targets: list[np.ndarray], about: np.ndarray | None = None
) -> np.ndarray:
    """(S, J) `NEAR_PERCENTILE` distance from the carried `produced[s]` to the nearest real frame,
    measured about `about` (S, J, 4; default the carry's means)."""
    about = carry.mean if about is None else about
    out = np.zeros(carry.mean.shape[:2])
    for s, (q, real) in enumerate(zip(produced, targets)):
        w = np.zeros((len(q), len(produced)))
        w[:, s] = 1.0
        out[s] = np.percentile(nearest_real(real, about[s], carry(q, w)), NEAR_PERCENTILE, axis=0)
    return out


def run_network_rotations(model: Any, styles: Sequence[str] | None = None) -> list[np.ndarray]:
    """`network_rotations` of running neutral clips, arms as streamed, other joints the input's."""
    inputs = _running_inputs()
    produced = network_rotations(model, inputs, leaf_prior=False, styles=styles)
    arms = [model.skeleton.index(n) for n in RUN_ARMS]
    for own, leafed in zip(produced, network_rotations(model, inputs, styles=styles)):
        own[:, arms] = leafed[:, arms]
    return produced


def network_rotations(
    model: Any, inputs: list, leaf_prior: bool = True, styles: Sequence[str] | None = None
) -> list[np.ndarray]:
    """Per style: rotations (N, J, 4) of `inputs` as the network streams them, before the output prior."""
    from ..eval.run import stylise

    saved = model.stages
    leaf = saved.leaf_prior
    leaf = replace(leaf, run=None) if leaf_prior and isinstance(leaf, SlowPrior) else None
    model.stages = saved.replace(leaf_prior=leaf, output_prior=None, hinge_floor=None, twist_range=None)
    try:
        ks = [model.styles().index(s) for s in styles or model.styles()]
        outs = stylise(model, [m for _ in ks for m in inputs], [k for k in ks for _ in inputs])
    finally:
        model.stages = saved
    n = len(inputs)
    return [comparable(np.concatenate([o.rotations for o in outs[i * n : (i + 1) * n]])) for i in range(len(ks))]
