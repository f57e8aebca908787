"""A quick guard on what a skinned character shows: the committed weights stepped over a few
validation clips toward every style, scored with `models.eval`'s rotation plausibility and
planted-toe slide against real data of the style.

The old issue-#14 gates were every joint >= 95 % rotation-plausible and planted-toe median slide
<= 2x real; the sealed evaluation (docs/evaluation.md) now judges by measures no clamp enforces.
This test holds each method to what its committed weights reach today (`FLOORS`, `POPS`),
measured the same way: a change that makes any method's rotations, planted feet or frame-to-frame
smoothness worse fails here. Raise a
floor when a model improves; the gate values are the goal."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import load_motions, select
from models.eval.plausibility import RotationReference
from models.eval.run import LOCOMOTION, stylise
from models.motion.features import body_joint
from models.motion.rotations import quat_angle
from models.motion.skeleton import Motion, Skeleton
from models.registry import load_models
from models.settings import get_settings

from .reference.foot_slide import planted_slide


def toe_slide(motions: list[Motion]) -> float:
    """Median planted-toe speed (cm/s) over clips, every clip's planted frames pooled."""
    v = np.concatenate([planted_slide(m)["toe"] for m in motions])
    return float(np.median(v)) if len(v) else 0.0


def upper_body(skeleton: Skeleton) -> list[int]:
    """The joints above the hips (spine, neck, head, arms): every descendant of the hips but the
    legs, whose rotations also follow wherever the foot planter holds the feet."""
    hips = body_joint(skeleton, "hips")
    legs = {body_joint(skeleton, "hip_l"), body_joint(skeleton, "hip_r")}
    out, stack = [], [c for c in skeleton.children(hips) if c not in legs]
    while stack:
        j = stack.pop()
        out.append(j)
        stack += skeleton.children(j)
    return sorted(out)


def lingering(fresh: list[Motion], running: list[Motion], seconds: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)) -> dict:
    """How long a session shows what came before it: at each time t into a clip, the median and
    p90 over clips of the worst upper-body joint's angle (degrees) between the clip's output in a
    running session and in a fresh one. 0 once the session has forgotten; a stateless method is 0
    from the first frame. Clips shorter than t are left out at t (no entry when all are)."""
    joints = upper_body(fresh[0].skeleton)
    out = {}
    for t in seconds:
        k = round(t * fresh[0].fps)
        angles = [
            float(np.degrees(quat_angle(a.rotations[k, joints], b.rotations[k, joints])).max())
            for a, b in zip(fresh, running)
            if a.num_frames > k
        ]
        if angles:
            out[f"{t:g}"] = {
                "median": float(np.median(angles)),
                "p90": float(np.percentile(angles, 90)),
                "clips": len(angles),
            }
    return out


DATASET = "bandai-namco-2"
STYLES = ("active", "elderly", "exhausted", "feminine", "masculine", "youthful")
FRAMES = 90
# per method: (lowest share of joint-frames within the real p99 rotation distance over the
# styles, worst joint; highest planted-toe median slide over the styles as a multiple of real)
# The slide ceiling is the gate since the shared foot planter (models.motion.feet): measured 0.0x for all three
# measured: within lti 0.97 (its rotation prior, models/motion/rotation_ball.py), erd 0.96 (its rotation prior,
# models/erd/rotation_prior.py), lpn 0.953 (its rotation prior, models/weights/lpn/rotation_prior.npz; 0.51
# without it; the worst joints left are legs, which the foot planter re-poses after the prior)
FLOORS = {"lti": (0.95, 2.0), "erd": (0.95, 2.0), "lpn": (0.95, 2.0)}
GATES = (0.95, 2.0)
# per method: the highest share of a joint's frames turning faster from frame to frame than the
# style's real p99.9 (`RotationReference.pops`), over the styles. Real validation walks and runs
# of each style score 0.011-0.023; measured here: lti 0.185 (elderly UpperArm_L: the input run's
# arm swing, at running pace where real elderly arms move slowly), erd 0.304 (elderly LowerArm_R;
# feminine and youthful Head 0.09, 0.21 before its priors carried only the slow part of each
# rotation, models/erd/slow_carry.py), lpn 0.045
POPS = {"lti": 0.2, "erd": 0.33, "lpn": 0.06}


def _clips(index, style: str, contents: tuple[str, ...], per_content: int, split: str = "val"):
    clips = select(index, dataset=DATASET, split=split, style=style)
    return [
        c
        for content in contents
        for c in sorted((c for c in clips if c.content == content), key=lambda c: c.name)[:per_content]
    ]


@pytest.fixture(scope="module")
def reference(index) -> RotationReference:
    return RotationReference({s: load_motions(select(index, dataset=DATASET, split="train", style=s)) for s in STYLES})


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


@pytest.mark.parametrize("method", sorted(FLOORS))
def test_rotations_and_planted_feet_stay_where_the_committed_weights_keep_them(method, index, reference, models):
    model = models[method]
    contents = ("walk", "run")  # where planted feet matter, and all LPN-FiLM (a locomotion controller) is for
    assert set(contents) <= set(LOCOMOTION)
    inputs = [m.slice(0, FRAMES) for m in load_motions(_clips(index, "normal", contents, 2))]
    worst_within, worst_slide, worst_pops = 1.0, 0.0, 0.0
    for style in STYLES:
        outputs = stylise(model, inputs, [model.styles().index(style)] * len(inputs))
        real = [m.slice(0, FRAMES) for m in load_motions(_clips(index, style, contents, 2))]
        within = reference.plausibility(style, outputs)["min_within"]
        slide = toe_slide(outputs) / max(toe_slide(real), 0.5)  # 0.5 cm/s floor
        pops = reference.pops(style, outputs)["pops_max"]
        assert np.isfinite(within) and np.isfinite(slide)
        worst_within, worst_slide, worst_pops = (
            min(worst_within, within),
            max(worst_slide, slide),
            max(worst_pops, pops),
        )
    floor_within, ceiling_slide = FLOORS[method]
    print(
        f"{method}: worst joint within p99 {worst_within:.3f} (floor {floor_within}, gate {GATES[0]}), "
        f"toe slide {worst_slide:.1f}x real (ceiling {ceiling_slide}, gate {GATES[1]}), "
        f"pops {worst_pops:.3f} (ceiling {POPS[method]})"
    )
    assert worst_within >= floor_within
    assert worst_slide <= ceiling_slide
    assert worst_pops <= POPS[method]


# How long a session shows what came before (`lingering`: the worst upper-body
# joint's angle between a clip's output after 10 s of other clips and in a fresh session, p90):
# (seconds into the clip, ceiling in degrees). LTI's modes decay within ~10 frames (each
# eigenvalue capped at 0.9; at 0.995 a raised arm stayed out through 5 s of walking: 13.5 degrees
# at 2 s); Style-ERD's LSTMs forget more slowly (measured over these clips: 0.8 degrees at 4 s).
# LPN-FiLM, a controller with its own gait phase, has no such point.
FORGETS = {"lti": (2.0, 1.0), "erd": (4.0, 3.0)}


@pytest.mark.parametrize("method", sorted(FORGETS))
def test_a_session_forgets_a_gesture_while_it_walks_on(method, index, models):
    from models.eval.run import run_after_history

    model = models[method]
    # a raise-up and a wave, then walks: each walk streamed after the gestures (and the other walk)
    clips = _clips(index, "normal", ("raise-up-right-hand", "wave-both-hands", "walk"), 2)
    inputs = [m.slice(0, 150) for m in load_motions(clips)]
    walks = [i for i, c in enumerate(clips) if c.content == "walk"]
    _, running = run_after_history(model, inputs, ["active", "elderly"])
    fresh = {s: stylise(model, inputs, [model.styles().index(s)] * len(inputs)) for s in ("active", "elderly")}
    after, ceiling = FORGETS[method]
    linger = lingering(
        [fresh[s][i] for s in fresh for i in walks], [running[s][i] for s in fresh for i in walks], (after,)
    )[f"{after:g}"]
    print(f"{method}: upper body {after:g} s into a walk after gestures, p90 {linger['p90']:.2f} degrees")
    assert linger["p90"] <= ceiling
