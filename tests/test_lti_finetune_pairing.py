"""LTI fine-tuning pairs an upload with neutral clips doing the same (issue 47): a straight walk
with straight walks of similar pace, read from the motion, never from the upload's labels."""

from __future__ import annotations

import numpy as np
import pytest

from models.data.archives import is_available
from models.lti import finetune as ft
from models.lti import representation as rep
from models.lti.model import WEIGHTS_DIR, LTIStyleModel

FPS = 30.0


def _walk_features(frames: int, speed_cm: float, turn_deg_s: float, sway_deg: float) -> np.ndarray:
    """Synthetic (F, 67) features: forward steps, a steady turn, a pelvis swing of one stride per
    second (two steps) and a hips bob at two steps per second."""
    t = np.arange(frames) / FPS
    f = np.zeros((frames, rep.FEATURE_DIM))
    f[1:, 1] = speed_cm / FPS
    swing = np.radians(sway_deg) * np.sin(2 * np.pi * 1.0 * t)
    f[1:, 2] = np.radians(turn_deg_s) / FPS + np.diff(swing)
    f[:, 3] = 90.0 + 2.0 * np.cos(2 * np.pi * 2.0 * t)
    return f


def test_content_descriptor_reads_path_not_pelvis_swing() -> None:
    straight = np.exp(ft.content_descriptor(_walk_features(240, 110.0, 0.0, 15.0)))
    turning = np.exp(ft.content_descriptor(_walk_features(240, 110.0, 25.0, 0.0)))
    assert straight[0] - 0.1 == pytest.approx(1.1, rel=0.02)  # m/s
    assert straight[1] - 1.0 < 1.0  # a wide pelvis swing is no turn
    assert turning[1] - 1.0 == pytest.approx(25.0, rel=0.1)
    assert straight[2] - 0.5 == pytest.approx(2.0, abs=0.15)  # steps per second


@pytest.fixture(scope="module")
def bank_and_ref():
    if not is_available("bandai-namco-2"):
        pytest.skip("Bandai Namco dataset 2 not available")
    translators = LTIStyleModel(weights_dir=WEIGHTS_DIR, off=("raised_arm",)).translators
    ref = next(iter(translators.values())).ref
    return ft.neutral_bank(np.ascontiguousarray(ref, dtype=np.float64).tobytes()), ref


def test_real_walk_upload_pairs_with_straight_walks_of_similar_pace(bank_and_ref) -> None:
    from models.data import build_index, load_motions, select

    bank, ref = bank_and_ref
    contents = {c.name: c.content for c in select(build_index(["bandai-namco-2"]), dataset="bandai-namco-2")}
    walks = {c.name: c for c in bank.clips if contents[c.name] == "walk"}
    d1 = sorted(
        (c for c in select(build_index(["bandai-namco-1"]), dataset="bandai-namco-1") if c.content == "walk"),
        key=lambda c: c.name,
    )
    # a slow, upright walk and a fast, wide one: posture far from neutral either way
    uploads = [c for c in d1 if c.style in ("proud", "giant")][::2]
    assert len(uploads) == 2
    for clip, motion in zip(uploads, load_motions(uploads)):
        feats = rep.motion_to_features(motion.slice(0, 240), ref)
        paired = ft.nearest_neutral(bank, feats, int(ft.FINETUNE["pairs"]), len(feats))
        assert [contents[c.name] for c in paired] == ["walk"] * len(paired), clip.name
        speed = float(np.exp(ft.content_descriptor(feats)[0])) - 0.1
        gaps = sorted(abs(np.exp(c.content[0]) - 0.1 - speed) for c in walks.values())
        for c in paired:  # at most 0.1 m/s further in pace than the k closest-paced straight walks
            assert abs(np.exp(c.content[0]) - 0.1 - speed) <= gaps[len(paired) - 1] + 0.1, (clip.name, c.name)


def _neutral(frames: int, steps_per_s: float) -> ft.NeutralClip:
    content = np.log(np.array([1.2, 1.0, steps_per_s + 0.5]))
    return ft.NeutralClip("n", frames, np.zeros((frames, rep.FEATURE_DIM)), np.zeros(4), content)


def test_a_neutral_clip_is_cut_to_the_uploads_step_count() -> None:
    """Paired uncut, a slow-stepping upload's few steps are aligned to more neutral steps and the
    translator learns to shuffle: the neutral clip is cut to as many steps, within the warp's range."""
    lo, hi = ft.warpable()
    clip = _neutral(300, 1.8)
    assert ft.step_matched(clip, 240, 1.2, 300) == 160  # 8 steps at 1.2/s -> 8 steps at 1.8/s
    assert ft.step_matched(clip, 240, 1.2, 300, match=False) == 300
    assert ft.step_matched(clip, 120, 3.6, 300) == 240
    assert ft.step_matched(clip, 240, 0.2, 300) >= 240 / hi  # no shorter than the warp can stretch
    assert ft.step_matched(_neutral(100, 1.8), 120, 3.6, 300) == 100  # no longer than the clip
    assert lo <= 240 / ft.step_matched(clip, 240, 1.2, 300) <= hi


def test_an_upload_gets_a_rotation_prior_from_its_clip_and_no_backward_hinge(bank_and_ref, tmp_path) -> None:
    """An uploaded style gets the stages a built-in one has, fitted from its clip: its rotation
    ball (kept when saved) and, from the model, the hinge floors; its output on a validation walk
    bends no knee or elbow backward past the least real bend."""
    from models.data import build_index, load_motion, select
    from models.lti.model import StyleTranslator
    from models.motion.hinge import kernel_floor
    from models.motion.rotations import quat_log, swing_twist

    _, ref = bank_and_ref
    index = build_index(["bandai-namco-1", "bandai-namco-2"])
    giant = sorted((c for c in select(index, dataset="bandai-namco-1", style="giant") if c.content == "walk"), key=str)
    tr = ft.fine_tune(load_motion(giant[0]), "giant", ref).translator
    assert tr.prior_mean is not None and tr.prior_radii is not None and np.isfinite(tr.prior_radii[:, 1:]).all()
    tr.save(tmp_path / "t.npz")
    np.testing.assert_array_equal(StyleTranslator.load(tmp_path / "t.npz").prior_radii, tr.prior_radii)
    model = LTIStyleModel(weights_dir=WEIGHTS_DIR)
    model.install_style("upload", tr)
    assert model.hinges is not None
    walk = load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])
    out = model.translate(walk, "upload")[0].rotations
    bone, hinge, floor = kernel_floor(model.skeleton, model.hinges)
    for j in model.hinges.joints:
        assert (quat_log(swing_twist(out[:, j], bone[j])[0]) @ hinge[j]).min() >= floor[j] - 1e-9


def test_upload_pairs_are_warped_at_a_steady_rate(bank_and_ref) -> None:
    """The job's alignment advances the uploaded clip at a steady rate: uncharged, IMW's cheapest
    warp held the clip still for frames and then jumped (a quarter to over half of the frames at
    the least slope), and the training targets lost the motion between the held poses."""
    from models.data import SPLITS, build_index, load_motion, select

    bank, ref = bank_and_ref
    index = build_index(["bandai-namco-1", "bandai-namco-2"])
    clips = [
        sorted((c for c in select(index, dataset=d, style=s) if c.content == "walk" and c.split in splits), key=str)[0]
        for d, s, splits in (("bandai-namco-1", "happy", SPLITS), ("bandai-namco-2", "elderly", ("train",)))
    ]
    lo = 1.0 / ft.CONFIG["imw"]["s"]
    for clip in clips:
        motion = load_motion(clip).slice(0, 240)
        feats = rep.motion_to_features(motion, ref)
        neutral = ft.nearest_neutral(bank, feats, 1, len(feats))[0]
        cut = ft.step_matched(neutral, len(feats), ft.steps_per_second(ft.content_descriptor(feats)), 300)
        pair = ft.pair_from_motions(
            bank.motions[neutral.name].slice(0, cut), motion, bank.match_mean, bank.match_std, ref, ft.pairing_config()
        )
        slope = np.diff(pair.warp)
        assert np.mean(slope <= lo + 1e-9) < 0.2, clip.name
        assert np.mean(np.abs(np.diff(slope))) < 0.2, clip.name
