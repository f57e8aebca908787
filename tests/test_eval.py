"""Evaluation suite: judges load and score real clips, metric sanity, end-to-end quick run."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from models.data import build_index, load_motions, select
from models.eval import clip_features, load_judges
from models.eval.judges import weights_dir
from models.eval.metrics import foot_skating, frechet_distance, path_deviation

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
    assert path_deviation(m, m) == pytest.approx(0.0, abs=1e-9)
    shifted = m.translations.copy()
    shifted[:, 1, 0] += np.linspace(0, 30, m.num_frames)  # drift 0 -> 30 cm sideways
    from dataclasses import replace

    assert path_deviation(m, replace(m, translations=shifted)) == pytest.approx(15.0, rel=0.05)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 4))
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    assert frechet_distance(a, a + 2.0) == pytest.approx(16.0, rel=1e-3)
    s = foot_skating(m)
    assert 0.0 <= s["skate_ratio"] <= 1.0 and s["contact_frames"] > 0
    slid = m.translations.copy()
    slid[:, 1, 0] += np.arange(m.num_frames) * 40.0 / m.fps  # the whole body glides sideways at 40 cm/s
    glide = foot_skating(replace(m, translations=slid))
    assert glide["contact_frames"] == s["contact_frames"]  # same heights, same contacts
    assert glide["skate_ratio"] > 0.9 > 0.5 > s["skate_ratio"]
    lat = judges.latents([clip_features(x) for x in motions])
    assert lat.shape[1] == judges.dae.enc[-1].out_features and np.isfinite(lat).all()


def test_eval_end_to_end_quick(tmp_path):
    from models.eval.run import evaluate

    t = time.time()
    r = evaluate(quick=True, out_dir=tmp_path)
    assert time.time() - t < 30
    assert "identity" in r["methods"]
    ident = r["methods"]["identity"]["overall"]
    assert ident["path_dev_cm"] == pytest.approx(0.0, abs=1e-6)
    saved = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert set(saved["methods"]) == set(r["methods"])
    assert "| identity |" in (tmp_path / "evaluation.md").read_text()
    assert list((tmp_path / "eval").glob("grid_*.png"))


def test_a_missed_accuracy_gate_says_how_many_clips_short_it_is():
    """30 of 34 is 88 %: one clip short of 90 % (31 of 34); passed gates are not listed."""
    from models.eval.run import _clips_short

    def row(style: float, content: float, clips: int) -> dict:
        ok = {"value": 1.0, "pass": True}
        return {
            "style": {"value": style, "pass": style >= 0.9},
            "style_rot": ok,
            "content": {"value": content, "pass": content >= 0.9},
            "clips": clips,
        }

    gates = {"erd": {"elderly": row(30 / 34, 1.0, 34), "fmd": {}}, "lpn": {"active": row(1.0, 7 / 13, 13)}}
    assert _clips_short(gates) == ["erd elderly style 30 of 34, 1 short", "lpn active content 7 of 13, 5 short"]


def test_the_validation_table_scores_validation_clips_and_names_each_miss(tmp_path):
    """`--split val` (what settings are chosen by) never scores a test clip, holds the methods
    against TRAIN clips, and lists every clip a judge misses with what it read."""
    from models.eval.run import evaluate

    r = evaluate(quick=True, out_dir=tmp_path, split="val", methods=("lti",), grids=False)
    meta = r["meta"]
    assert (meta["split"], meta["reference_split"]) == ("val", "train")
    val = {c.name for c in select(build_index(["bandai-namco-2"]), split="val", style="normal")}
    assert meta["clips"] and set(meta["clips"]) <= val
    for name, m in r["methods"].items():
        for style, p in m["per_style"].items():
            for key in ("style", "content"):
                missed = p["misses"][key]
                assert set(missed) <= set(meta["clips"])
                assert len(missed) == round((1 - p[f"{key}_acc"]) * p["clips"]), (name, style, key)
            assert all(read != style for read in p["misses"]["style"].values())
    assert "VALIDATION" in (tmp_path / "evaluation.md").read_text()


def test_only_the_test_and_validation_splits_can_be_scored():
    from models.eval.run import evaluate

    with pytest.raises(ValueError, match="split"):
        evaluate(quick=True, split="train")


def test_a_one_frame_flick_of_the_head_is_a_pop():
    """`RotationReference.pops`: a real clip turns no faster from frame to frame than the real
    data mostly does; the same clip with the head flicked 30 degrees for one frame pops there."""
    from dataclasses import replace

    from models.eval.plausibility import RotationReference, rotation_acceleration
    from models.motion.rotations import expmap_to_quat, quat_mul

    index = build_index(["bandai-namco-2"])
    ref = RotationReference({"elderly": load_motions(select(index, split="train", style="elderly"))})
    clip = load_motions(select(index, split="val", style="elderly", content="walk")[:1])[0].slice(0, 90)
    calm = ref.pops("elderly", [clip])
    head = clip.skeleton.index("Head")
    rot = clip.rotations.copy()
    rot[45, head] = quat_mul(rot[45, head], expmap_to_quat(np.radians([0.0, 30.0, 0.0])))
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
    from models.motion.rotations import expmap_to_quat, quat_mul
    from models.motion.twist import bone_axes

    index = build_index(["bandai-namco-2"])
    ref = RotationReference({"elderly": load_motions(select(index, split="train", style="elderly"))})
    clip = load_motions(select(index, split="val", style="elderly", content="walk")[:1])[0].slice(0, 90)
    arm = clip.skeleton.index("LowerArm_L")
    rot = clip.rotations.copy()
    rot[:, arm] = quat_mul(rot[:, arm], expmap_to_quat(np.radians(40.0) * bone_axes(clip.skeleton)[arm]))
    calm, wrung = ref.plausibility("elderly", [clip]), ref.plausibility("elderly", [replace(clip, rotations=rot)])
    assert calm["per_joint"]["LowerArm_L"]["twist_beyond_p95_deg"] == 0.0
    hi = np.degrees(ref.twist_range["elderly"][1, ref.joints.index("LowerArm_L")])
    beyond = wrung["per_joint"]["LowerArm_L"]["twist_beyond_p95_deg"]
    assert wrung["farthest_twist_joint"] == "LowerArm_L" and abs(beyond - (40.0 - hi)) < 6.0  # the clip's own spread
