"""Evaluation suite: judges load and score real clips, metric sanity, end-to-end quick run."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motions, select
from models.eval import clip_features, load_judges
from models.eval.judges import weights_dir
from models.eval.metrics import foot_skating

pytestmark = pytest.mark.skipif(not (weights_dir() / "judges.pt").exists(), reason="no eval judges committed")


@pytest.fixture(scope="module")
def judges():
    return load_judges()


@pytest.fixture(scope="module")
def test_clips():
    index = build_index(["bandai-namco-2"])
    clips = []
    for style in ("normal", "elderly", "feminine", "active"):
        for content in ("walk", "wave-both-hands", "raise-up-left-hand"):
            clips += select(index, split="test", style=style, content=content)[:1]
    return clips, load_motions(clips)


def test_classifiers_score_real_clips_above_chance(judges, test_clips):
    clips, motions = test_clips
    feats = [clip_features(m) for m in motions]
    style_acc = np.mean([p == c.style for p, c in zip(judges.predict_style(feats), clips)])
    content_acc = np.mean([p == c.content for p, c in zip(judges.predict_content(feats), clips)])
    assert style_acc > 2 / 7  # chance 1/7
    assert content_acc > 2 / 10  # chance 1/10
    assert judges.meta["test"]["style_acc"] > 0.5 and judges.meta["test"]["content_acc"] > 0.5


def test_own_style_is_recognised(judges, test_clips):
    clips, motions = test_clips
    feats = [clip_features(m) for m in motions]
    logp = judges.style_logprobs(feats)
    own = np.array([judges.styles.index(c.style) for c in clips])
    assert np.mean(np.exp(logp[np.arange(len(clips)), own])) > 0.5


def test_metric_sanity(judges, test_clips):
    _, motions = test_clips
    m = motions[0]
    from dataclasses import replace

    s = foot_skating(m)
    assert 0.0 <= s["skate_ratio"] <= 1.0 and s["contact_frames"] > 0
    slid = m.translations.copy()
    slid[:, 1, 0] += np.arange(m.num_frames) * 40.0 / m.fps  # the whole body glides sideways at 40 cm/s
    glide = foot_skating(replace(m, translations=slid))
    assert glide["contact_frames"] == s["contact_frames"]  # same heights, same contacts
    assert glide["skate_ratio"] > 0.9 > 0.5 > s["skate_ratio"]


def test_a_one_frame_flick_of_the_head_is_a_pop():
    """`RotationReference.pops`: a real clip turns no faster from frame to frame than the real
    data mostly does; the same clip with the head flicked 30 degrees for one frame pops there."""
    from dataclasses import replace

    from models.eval.plausibility import RotationReference, rotation_acceleration
    from models.motion.rotations import quat_exp, quat_mul

    index = build_index(["bandai-namco-2"])
    ref = RotationReference({"elderly": load_motions(select(index, split="train", style="elderly"))})
    clip = load_motions(select(index, split="val", style="elderly", content="walk")[:1])[0].slice(0, 90)
    calm = ref.pops("elderly", [clip])
    head = clip.skeleton.index("Head")
    rot = clip.rotations.copy()
    rot[45, head] = quat_mul(rot[45, head], quat_exp(np.radians([0.0, 30.0, 0.0])))
    flicked = replace(clip, rotations=rot)
    assert calm["pops_largest_deg"] < 15.0 and ref.pops("elderly", [flicked])["pops_largest_deg"] > 50.0
    k = ref.joints.index("Head")
    over = lambda m: int((rotation_acceleration(m, ref.joint_index)[:, k] > ref.pop_limit["elderly"][k]).sum())  # noqa: E731
    assert over(clip) == 0 and over(flicked) == 3  # the frame before, the flick, the frame after


def test_a_forearm_wrung_past_the_real_twists_reads_as_that_many_degrees_beyond():
    """`RotationReference.plausibility`: a real clip's twists lie inside the real interval (0
    degrees beyond at the p95); the same clip with the left forearm twisted 40 degrees about its
    bone reads about 40 degrees less the interval's upper end beyond it, on that joint."""
    from dataclasses import replace

    from models.eval.plausibility import RotationReference
    from models.motion.rotations import quat_exp, quat_mul
    from models.motion.twist import bone_axes

    index = build_index(["bandai-namco-2"])
    ref = RotationReference({"elderly": load_motions(select(index, split="train", style="elderly"))})
    clip = load_motions(select(index, split="val", style="elderly", content="walk")[:1])[0].slice(0, 90)
    arm = clip.skeleton.index("LowerArm_L")
    rot = clip.rotations.copy()
    rot[:, arm] = quat_mul(rot[:, arm], quat_exp(np.radians(40.0) * bone_axes(clip.skeleton)[arm]))
    calm, wrung = ref.plausibility("elderly", [clip]), ref.plausibility("elderly", [replace(clip, rotations=rot)])
    assert calm["per_joint"]["LowerArm_L"]["twist_beyond_p95_deg"] == 0.0
    hi = np.degrees(ref.twist_range["elderly"][1, ref.joints.index("LowerArm_L")])
    beyond = wrung["per_joint"]["LowerArm_L"]["twist_beyond_p95_deg"]
    assert wrung["farthest_twist_joint"] == "LowerArm_L" and abs(beyond - (40.0 - hi)) < 6.0  # the clip's own spread
