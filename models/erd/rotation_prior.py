"""The fits of Style-ERD's rotation priors (`slow_carry.SlowPrior`, `models.motion.style_carry`)
from real TRAIN clips, the same way for every style (`python -m models.erd fit`):

1. **Leaves** (`leaf_prior.npz`): the position-trained network never learned bone twists or the
   head, hands and toes, so those come from the input, first carried from the real neutral
   distribution to the real target style's.
2. **Output** (`output_prior.npz`): the network's rotations, carried from what it produces toward
   each style (streamed over TRAIN neutral clips) to the style's real distribution and clamped
   into its range. The legs are only clamped (the foot planter re-poses them; carried, they
   turned straight walks). Every other joint of a style is carried whole, by its mean's shift
   alone or only clamped, whichever brings the network's frames nearest the style's real frames
   (`output_carry`): since the network was distilled its own rotations often lie on the real
   ones already, and a Gaussian map's stretch moved them off (the head, for every style).
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
from ..motion.rotations import quat_exp, quat_inv, quat_log, quat_mul
from ..motion.style_carry import StyleCarry
from .dataset import STYLES, TARGET_STYLES
from .slow_carry import SlowPrior

LEAF_FILE = "leaf_prior.npz"  # each with its run prior beside it (`slow_carry.run_file`)
OUTPUT_FILE = "output_prior.npz"
FIXED = (ROOT, HIPS)  # joint_Root and Hips: their rotation holds the heading
FIT_CLIPS_PER_CONTENT = 4
RUN_FIT_CLIPS = 12  # TRAIN neutral clips that run, for the run output prior
FIT_FRAMES = 240
SUPPORT_FRAMES = 40_000  # real frames per style `nearest_real` measures against (evenly spread)
NEAR_PERCENTILE = 95.0  # of the distances to the nearest real frame `output_carry` compares
NEAR_MARGIN_DEG = 1.0  # how much nearer a lesser carry must bring them to replace the whole (validation)
# the share of the way from the network's rotations to the style's each carry goes: on validation
# 0.5 and 0.75 made more clips plausible and read fewer as their style (docs/eval/ablation.md)
CARRY_SHARE = 1.0
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
        return output_carry(produced, targets, clamped)

    walk = fitted(network_rotations(model, _neutral_inputs(), styles=styles), real_rotations(), (HIPS,) + legs)
    run = fitted(run_network_rotations(model, styles), real_rotations(runs=True), (HIPS,))
    return SlowPrior(tuple(styles), walk, run, HIPS)


def output_carry(produced: list[np.ndarray], targets: list[np.ndarray], clamped: tuple[int, ...]) -> StyleCarry:
    """Per style, the carry of the network's rotations `produced` (N, J, 4) to the real `targets`
    (N', J, 4), joint_Root left alone and the joints `clamped` only clamped; every other joint
    takes the whole carry unless its mean shift alone or the clamp alone brings the network's
    frames nearer the real ones (`near_percentile`) by `NEAR_MARGIN_DEG`, then the nearer of
    those: the whole carry also carries what a session streamed long from its start lost of its
    style, which frames of fresh sessions cannot show."""
    carry = StyleCarry.fit(produced, targets, (0,), clamp_only=clamped)
    kinds = (partial(carry, CARRY_SHARE), partial(mean_shift(carry), CARRY_SHARE), carry.bounds)
    far = np.stack([near_percentile(k, produced, targets) for k in kinds])  # (3, S, J)
    far[0] -= np.radians(NEAR_MARGIN_DEG)
    return chosen(kinds, np.argmin(far, axis=0))


def mean_shift(carry: StyleCarry) -> StyleCarry:
    """`carry` without its spread: each rotation turned by the move from the source mean to the
    style's (identity maps), then clamped."""
    same = np.ascontiguousarray(np.broadcast_to(np.eye(3), carry.map.shape))
    return StyleCarry(carry.source, carry.mean, same, carry.radius)


def partial(carry: StyleCarry, share: float) -> StyleCarry:
    """`carry` taken `share` of the way: the map (1 - share) I + share M, and the source mean
    carried `share` of the way to the style's mean (the source moved back by what the map makes
    of that landing's offset), so the clamp still holds the style's own range. An entry with
    nothing to carry (its source the style's mean, only clamped) is kept exactly."""
    if share == 1.0:
        return carry
    still = np.all(carry.source == carry.mean, axis=-1, keepdims=True)
    lin = np.where(still[..., None], carry.map, (1.0 - share) * np.eye(3) + share * carry.map)
    to = quat_mul(carry.source, quat_exp(share * quat_log(quat_mul(quat_inv(carry.source), carry.mean))))
    back = np.linalg.solve(lin, quat_log(quat_mul(quat_inv(carry.mean), to))[..., None])[..., 0]
    source = np.where(still, carry.source, quat_mul(carry.source, quat_exp(-back)))
    return StyleCarry(np.ascontiguousarray(source), carry.mean, np.ascontiguousarray(lin), carry.radius)


def chosen(kinds: Sequence[StyleCarry], choice: np.ndarray) -> StyleCarry:
    """One carry whose (style, joint) entries come from `kinds[choice[s, j]]` (carries that share
    their style means and radii)."""
    source = np.take_along_axis(np.stack([k.source for k in kinds]), choice[None, ..., None], 0)[0]
    lin = np.take_along_axis(np.stack([k.map for k in kinds]), choice[None, ..., None, None], 0)[0]
    return StyleCarry(source, np.array(kinds[0].mean), lin, np.array(kinds[0].radius))


def nearest_real(real: np.ndarray, mean: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(N, J) distance (the rotation vector about `mean` (J, 4), as the evaluation's rotation
    support measures it) from each rotation of `q` (N, J, 4) to the nearest of `real` (M, J, 4),
    evenly subsampled to `SUPPORT_FRAMES`."""
    from scipy.spatial import cKDTree

    real = real[np.linspace(0, len(real) - 1, min(len(real), SUPPORT_FRAMES)).astype(int)]
    pts = quat_log(quat_mul(quat_inv(mean)[None], real))
    x = quat_log(quat_mul(quat_inv(mean)[None], q))
    return np.stack([cKDTree(pts[:, j]).query(x[:, j])[0] for j in range(q.shape[1])], axis=1)


def near_percentile(carry: StyleCarry, produced: list[np.ndarray], targets: list[np.ndarray]) -> np.ndarray:
    """(S, J) the `NEAR_PERCENTILE` distance from style s's carried frames of `produced[s]` to the
    nearest of its real frames `targets[s]`: the same test for every style and joint (a
    distribution's mean and spread can match the style's while its frames lie off the real ones,
    which a per-joint Gaussian map cannot see)."""
    out = np.zeros(carry.mean.shape[:2])
    for s, (q, real) in enumerate(zip(produced, targets)):
        w = np.zeros((len(q), len(produced)))
        w[:, s] = 1.0
        out[s] = np.percentile(nearest_real(real, carry.mean[s], carry(q, w)), NEAR_PERCENTILE, axis=0)
    return out


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
    prior (not its run prior) where `leaf_prior`, and none of the stages from the output prior on
    (what the output priors carry from)."""
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
