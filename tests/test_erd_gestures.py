"""Style-ERD, toward every style: a raised hand's output prior follows what the hand does
(`models/erd/gestures.py`): a waving hand takes the prior fitted on raised hands, a still raised
arm the prior fitted on raised, still arms of its side, the other arm the prior fitted on arms
hanging while the other hand is up; with no style asked for, or both hands down, nothing changes."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from models.motion.rotations import quat_angle

from .clips import streamed_rotations

WEIGHTS = Path(__file__).resolve().parents[1] / "models" / "weights" / "erd"

pytestmark = pytest.mark.skipif(
    not (WEIGHTS / "output_prior_gesture.npz").exists(), reason="Style-ERD gesture prior not committed"
)


@pytest.fixture(scope="module")
def model():
    import models.erd

    return models.erd.load(WEIGHTS)


def _val(index, content: str, n: int = 1, frames: int = 90):
    from models.data import load_motions, select

    clips = select(index, dataset="bandai-namco-2", split="val", style="normal", content=content)[:n]
    return [m.slice(0, frames) for m in load_motions(clips)]


@pytest.fixture(scope="module")
def raise_up(index):
    return _val(index, "raise-up-left-hand")[0]


@pytest.fixture(scope="module")
def wave(index):
    return _val(index, "wave-left-hand")[0]


def _weights(model, **mix: float) -> np.ndarray:
    w = np.zeros(len(model.styles()))
    for style, x in mix.items():
        w[model.styles().index(style)] = x
    return w


def _shares(model, motion) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2) each hand's raise share and wave share, as the stream measures them."""
    from models.erd.features import FPS
    from models.motion.hands import clip_sway, hand_offsets, raise_share, side_heights, wave_share

    pos = model.maker.positions(motion.translations[:, 1], motion.rotations)
    return raise_share(side_heights(pos)), wave_share(clip_sway(hand_offsets(pos), FPS))


def test_the_sway_tells_a_wave_from_a_raise_up(model, index):
    """On the frames with the hand up, a validation wave's hand sways past the ramp and a
    raise-up's stays below it."""
    for content, waving in (("wave-left-hand", 1.0), ("raise-up-left-hand", 0.0)):
        for motion in _val(index, content, n=3, frames=150):
            raised, waves = _shares(model, motion)
            up = raised[:, 0] == 1.0
            assert up.sum() >= 10
            assert np.median(waves[up, 0]) == waving


STYLES = ("active", "elderly", "exhausted", "feminine", "masculine", "youthful")


@pytest.mark.parametrize("style", ["feminine", "active", "elderly", "masculine"])
def test_a_waving_hand_takes_the_gesture_prior(model, wave, style):
    """Frames with the hand waving are carried by the gesture prior, toward any style; until a
    hand goes up the frames are exactly what the all-content prior alone gives."""
    without = copy.copy(model)
    without.gesture_prior = None
    w = _weights(model, **{style: 1.0})
    raised, waves = _shares(model, wave)
    got, before = streamed_rotations(model, wave, w), streamed_rotations(without, wave, w)
    waving = (raised * waves).max(-1) == 1.0
    down = np.cumsum(raised.max(-1)) == 0.0  # both hands down so far
    assert waving.sum() >= 10 and down.sum() >= 5
    assert np.median(np.degrees(quat_angle(got, before))[waving].max(axis=-1)) > 2.0
    np.testing.assert_array_equal(got[down], before[down])


def test_no_style_and_a_walk_stream_as_before(model, index, raise_up, wave):
    """The arm priors move nothing where no style is asked for, nor on a walk (no hand raised)."""
    without = copy.copy(model)
    without.gesture_prior = without.raise_prior = without.hanging_prior = None
    for motion in (raise_up, wave):
        none = np.zeros(len(model.styles()))
        np.testing.assert_array_equal(
            streamed_rotations(model, motion, none), streamed_rotations(without, motion, none)
        )
    walk = _val(index, "walk")[0]
    w = _weights(model, masculine=0.6, exhausted=0.4)
    np.testing.assert_array_equal(streamed_rotations(model, walk, w), streamed_rotations(without, walk, w))


def _only_the_arm_moves(model, motion, prior: str, style: str, side: str, frames: np.ndarray, raised) -> None:
    """Toward `style`, with and without the model's `prior`: on `frames` the `side` arm moved and
    the spine, head and other arm exactly as they were; before any hand goes up every joint."""
    from models.erd.gestures import ARM_JOINTS

    without = copy.copy(model)
    setattr(without, prior, None)
    w = _weights(model, **{style: 1.0})
    down = np.cumsum(raised.max(-1)) == 0.0
    assert frames.sum() >= 10 and down.sum() >= 5
    got, before = streamed_rotations(model, motion, w), streamed_rotations(without, motion, w)
    other = "R" if side == "L" else "L"
    arm = [model.skeleton.index(f"{j}_{side}") for j in ARM_JOINTS]
    rest = [model.skeleton.index(j) for j in ("Spine", "Chest", "Neck", "Head")]
    rest += [model.skeleton.index(f"{j}_{other}") for j in ARM_JOINTS]
    assert np.median(np.degrees(quat_angle(got, before))[frames][:, arm].max(axis=-1)) > 1.0
    np.testing.assert_array_equal(got[frames][:, rest], before[frames][:, rest])
    np.testing.assert_array_equal(got[down], before[down])


@pytest.mark.parametrize("style", ["active", "elderly"])
def test_a_still_raised_hand_takes_the_raise_prior_on_its_arm_alone(model, raise_up, style):
    """On a raise-up's frames with the hand up and still, the raised side's arm is carried by the
    raise prior and the rest of the upper body is what it was without it (the legs are the foot
    planter's, which remembers the frames before); until the hand goes up every joint is as before."""
    from models.erd.features import FPS
    from models.motion.hands import clip_sway, hand_offsets, still_share

    raised, _ = _shares(model, raise_up)
    pos = model.maker.positions(raise_up.translations[:, 1], raise_up.rotations)
    still = still_share(clip_sway(hand_offsets(pos), FPS))[:, 0] == 1.0
    frames = (raised[:, 0] == 1.0) & still & (raised[:, 1] == 0.0)
    _only_the_arm_moves(model, raise_up, "raise_prior", style, "L", frames, raised)


@pytest.mark.parametrize("style", ["active", "feminine"])
def test_the_hanging_arm_takes_the_hanging_prior_alone(model, raise_up, style):
    """While the left hand is up and the right one down, the right arm is carried by the hanging
    prior and nothing else moves; before the hand goes up every joint is as before."""
    raised, _ = _shares(model, raise_up)
    frames = (raised[:, 0] == 1.0) & (raised[:, 1] == 0.0)
    _only_the_arm_moves(model, raise_up, "hanging_prior", style, "R", frames, raised)


@pytest.mark.parametrize("prior", ["raise_prior", "hanging_prior"])
def test_the_arm_priors_are_fitted_on_both_arms_of_every_style(model, prior):
    """The committed raise and hanging priors: both arms fitted anew for every style, every other
    joint the all-content prior's maps."""
    from models.erd.gestures import ARM_JOINTS

    arms = {model.skeleton.index(f"{j}_{s}") for j in ARM_JOINTS for s in "LR"}
    for s, style in enumerate(model.styles()):
        for j in range(len(model.skeleton.names)):
            pairs = zip(getattr(model, prior).arrays, model.output_prior.arrays)
            same = all(np.array_equal(a[s, j], b[s, j]) for a, b in pairs)
            assert same == (j not in arms), (style, model.skeleton.names[j])


def test_the_gesture_prior_is_fitted_for_every_style(model):
    for s, style in enumerate(model.styles()):
        same = [np.array_equal(a[s], b[s]) for a, b in zip(model.gesture_prior.arrays, model.output_prior.arrays)]
        assert not all(same), style


def test_arm_frames_split_each_styles_waves_from_its_raise_ups(index):
    """`rotation_prior.arm_frames`, what the arm priors are fitted on: each style's clips that wave
    are told from those that hold a hand up by the style's own sway (elderly waves sway less than
    normal raise-ups), and a held left hand is never also hanging."""
    from models.data import load_motions, select
    from models.erd.rotation_prior import arm_frames

    for style in ("elderly", "active"):
        clips = [
            c
            for c in select(index, dataset="bandai-namco-2", split="train", style=style)
            if c.content in ("raise-up-left-hand", "wave-left-hand")
        ][::4]
        for clip, frames in zip(clips, arm_frames(load_motions(clips))):
            waves = clip.content.startswith("wave")
            assert frames["waving"].any() == waves, (style, clip.name)
            assert frames["still_L"].any() != waves, (style, clip.name)
            assert not (frames["still_L"] & frames["hanging_L"]).any()


@pytest.mark.parametrize(
    "style,clip", [("feminine", "raise_up"), ("feminine", "wave"), ("elderly", "wave"), ("active", "raise_up")]
)
def test_a_gesture_streamed_equals_the_whole_clip(model, request, style, clip):
    """The offline path (`offline.stylise`) picks the gesture, raise and hanging priors frame by
    frame as the stream does."""
    from models.erd.offline import stylise

    motion, w = request.getfixturevalue(clip), _weights(model, **{style: 1.0})
    whole = stylise(model.torch_generator(), model.maker, motion, w, **model.priors)
    np.testing.assert_allclose(model.stylise_stream(motion, w).rotations, whole.rotations, atol=2e-4)


def test_validation_left_raise_ups_read_as_raise_ups(model, index):
    """What the arm priors are for: the content judge (trained on real TRAIN clips) reads these 4
    validation left-hand raise-ups, streamed toward each of the six styles, as raise-ups in at
    least 19 of the 24 outputs (the committed priors: 19, two misread toward feminine and
    masculine, one toward elderly; the per-style rules these replaced read 35 of 36 on the first
    6 such clips)."""
    from models.eval.features import clip_features
    from models.eval.judges import load_judges
    from models.eval.run import stylise

    inputs = _val(index, "raise-up-left-hand", n=4, frames=150)
    read = 0
    for style in STYLES:
        outs = stylise(model, inputs, [model.styles().index(style)] * len(inputs))
        got = load_judges().predict_content([clip_features(o) for o in outs])
        read += sum(g == "raise-up-left-hand" for g in got)
    assert read >= 19
