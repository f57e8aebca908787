"""Style-ERD toward feminine, youthful and active: a raised hand's output prior follows what the
hand does (`models/erd/gestures.py`): a waving hand takes the prior fitted on gestures, a still
raised arm the network's own upper arm and forearm (feminine, youthful) or the prior fitted on
raise-ups (active), and every other style streams exactly as before."""

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


@pytest.mark.parametrize("intensity", [1.0, 1.5])
def test_a_still_raised_arm_toward_feminine_is_the_networks_own(model, raise_up, intensity):
    """While the raised hand holds still, its upper arm and forearm are the network's (with its
    leaf prior) kept in the style's range, at any intensity; the rest of the upper body is still
    carried."""
    from models.erd.gestures import HELD_JOINTS
    from models.motion.bn_skeleton import HIPS

    shipped = copy.copy(model)
    shipped.twist_range = None  # applied after either; off, the arms compare as the priors leave them
    bare = copy.copy(shipped)
    bare.output_prior = None
    w = _weights(model, feminine=intensity)
    raised, waves = _shares(model, raise_up)
    held = (raised[:, 0] == 1.0) & (waves.max(-1) == 0.0)
    assert held.sum() >= 10
    network = model.output_prior.bounds(streamed_rotations(bare, raise_up, w), np.tile(w, (len(held), 1)), hips=HIPS)
    moved = np.degrees(quat_angle(streamed_rotations(shipped, raise_up, w), network))[held]
    arm = [model.skeleton.index(f"{j}_L") for j in HELD_JOINTS]
    rest = [
        model.skeleton.index(j) for j in ("Spine", "Chest", "Neck", "Head", "Shoulder_L", "UpperArm_R", "LowerArm_R")
    ]
    assert moved[:, arm].max() < 1e-3
    assert np.median(moved[:, rest].max(axis=-1)) > 2.0


@pytest.mark.parametrize("style", ["feminine", "active"])
def test_a_waving_hand_takes_the_gesture_prior(model, wave, style):
    """Frames with the hand waving are carried by the gesture prior; until a hand goes up the
    frames are exactly what the all-content prior alone gives."""
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


@pytest.mark.parametrize("mix", [{"masculine": 1.0}, {"elderly": 1.0}, {"masculine": 0.6, "exhausted": 0.4}])
def test_other_styles_stream_as_before(model, raise_up, wave, mix):
    """`GESTURE_STYLES` only: every other style and mix of them is untouched, raised hand or not."""
    without = copy.copy(model)
    without.gesture_prior = None
    w = _weights(model, **mix)
    for motion in (raise_up, wave):
        np.testing.assert_array_equal(streamed_rotations(model, motion, w), streamed_rotations(without, motion, w))


def _only_the_arm_moves(model, motion, prior: str, side: str, frames: np.ndarray, raised: np.ndarray) -> None:
    """Toward active, with and without the model's `prior`: on `frames` the `side` arm moved and
    the spine, head and other arm exactly as they were; before any hand goes up every joint."""
    from models.erd.gestures import ARM_JOINTS

    without = copy.copy(model)
    setattr(without, prior, None)
    w = _weights(model, active=1.0)
    down = np.cumsum(raised.max(-1)) == 0.0
    assert frames.sum() >= 10 and down.sum() >= 5
    got, before = streamed_rotations(model, motion, w), streamed_rotations(without, motion, w)
    other = "R" if side == "L" else "L"
    arm = [model.skeleton.index(f"{j}_{side}") for j in ARM_JOINTS]
    rest = [model.skeleton.index(j) for j in ("Spine", "Chest", "Neck", "Head")]
    rest += [model.skeleton.index(f"{j}_{other}") for j in ARM_JOINTS]
    assert np.median(np.degrees(quat_angle(got, before))[frames][:, arm].max(axis=-1)) > 2.0
    np.testing.assert_array_equal(got[frames][:, rest], before[frames][:, rest])
    np.testing.assert_array_equal(got[down], before[down])


def test_a_still_raised_hand_toward_active_takes_the_raise_up_prior_on_its_arm_alone(model, raise_up):
    """Toward active (`RAISED_STYLES`), on a raise-up's frames with the hand up and still, the
    raised side's arm is carried by the raise-up prior and the rest of the upper body is what it
    was without it (the legs are the foot planter's, which remembers the frames before); until
    the hand goes up every joint is as before."""
    from models.erd.features import FPS
    from models.motion.hands import clip_sway, hand_offsets, still_share

    raised, _ = _shares(model, raise_up)
    pos = model.maker.positions(raise_up.translations[:, 1], raise_up.rotations)
    still = still_share(clip_sway(hand_offsets(pos), FPS))[:, 0] == 1.0
    _only_the_arm_moves(
        model, raise_up, "raise_prior", "L", (raised[:, 0] == 1.0) & still & (raised[:, 1] == 0.0), raised
    )


def test_the_raise_up_prior_is_fitted_for_active_s_arms_alone(model):
    """The committed raise-up prior: active's arm joints fitted anew, every other joint and style
    the all-content prior's maps (a mix carries them as before)."""
    from models.erd.gestures import ARM_JOINTS, RAISED_STYLES

    arms = {model.skeleton.index(f"{j}_{s}") for j in ARM_JOINTS for s in "LR"}
    for s, style in enumerate(model.styles()):
        for j in range(len(model.skeleton.names)):
            same = all(
                np.array_equal(a[s, j], b[s, j]) for a, b in zip(model.raise_prior.arrays, model.output_prior.arrays)
            )
            assert same == (style not in RAISED_STYLES or j not in arms), (style, model.skeleton.names[j])


def test_toward_active_the_hanging_right_arm_takes_the_hanging_prior_alone(model, raise_up):
    """While the left hand is up and the right one down, toward active the right arm is carried by
    the hanging prior and nothing else moves; before the hand goes up every joint is as before."""
    raised, _ = _shares(model, raise_up)
    _only_the_arm_moves(model, raise_up, "hanging_prior", "R", (raised[:, 0] == 1.0) & (raised[:, 1] == 0.0), raised)


def test_the_hanging_prior_is_fitted_for_active_s_right_arm_alone(model):
    """The committed hanging prior: active's right arm fitted anew (`HANGING_SIDES`), every other
    joint and style the all-content prior's maps."""
    from models.erd.gestures import ARM_JOINTS, HANGING_SIDES, RAISED_STYLES

    arms = {model.skeleton.index(f"{j}_{s}") for j in ARM_JOINTS for s in HANGING_SIDES}
    for s, style in enumerate(model.styles()):
        for j in range(len(model.skeleton.names)):
            pairs = zip(model.hanging_prior.arrays, model.output_prior.arrays)
            same = all(np.array_equal(a[s, j], b[s, j]) for a, b in pairs)
            assert same == (style not in RAISED_STYLES or j not in arms), (style, model.skeleton.names[j])


def test_the_gesture_prior_keeps_the_other_styles_maps(model):
    """The committed gesture prior: fitted anew for the gesture styles, the all-content prior's
    maps for the rest (a mix carries them as before)."""
    from models.erd.gestures import GESTURE_STYLES

    for s, style in enumerate(model.styles()):
        same = [np.array_equal(a[s], b[s]) for a, b in zip(model.gesture_prior.arrays, model.output_prior.arrays)]
        assert all(same) == (style not in GESTURE_STYLES)


@pytest.mark.parametrize(
    "style,clip", [("feminine", "raise_up"), ("feminine", "wave"), ("youthful", "wave"), ("active", "raise_up")]
)
def test_a_gesture_streamed_equals_the_whole_clip(model, request, style, clip):
    """The offline path (`offline.stylise`) picks the gesture prior, the raise-up prior or the
    network's arm frame by frame as the stream does."""
    from models.erd.offline import stylise

    motion, w = request.getfixturevalue(clip), _weights(model, **{style: 1.0})
    whole = stylise(model.torch_generator(), model.maker, motion, w, **model.priors)
    np.testing.assert_allclose(model.stylise_stream(motion, w).rotations, whole.rotations, atol=2e-4)


def test_validation_left_raise_ups_toward_feminine_read_as_feminine_raise_ups(model, index):
    """What it is for: with the all-content prior on the raised arm, the content judge read every
    one of these 4 validation raise-ups toward feminine as a wave and the rotation judge 2 as
    youthful; now both judges (trained on real TRAIN clips) read all 4 right."""
    from models.eval.features import clip_features, rotation_features
    from models.eval.judges import load_judges, load_rotation_judge
    from models.eval.run import stylise

    inputs = _val(index, "raise-up-left-hand", n=4, frames=150)
    outs = stylise(model, inputs, [model.styles().index("feminine")] * len(inputs))
    assert load_judges().predict_content([clip_features(o) for o in outs]) == ["raise-up-left-hand"] * 4
    assert load_rotation_judge().predict_style([rotation_features(o) for o in outs]) == ["feminine"] * 4


@pytest.mark.parametrize("content,n", [("raise-up-both-hands", 4), ("wave-left-hand", 3)])
def test_validation_gestures_toward_active_read_as_active(model, index, content, n):
    """What the raise-up and hanging priors are for: with the all-content prior on the arms the
    rotation judge read 1 of these 4 validation raise-ups with both hands toward active as
    masculine (log-odds over the next style -0.05..+1.69; raise-up prior: +0.85..+2.44), and 1
    of the 3 left-hand waves (-0.63..+5.96; hanging prior: +3.85..+4.24); now all of them."""
    from models.eval.features import rotation_features
    from models.eval.judges import load_rotation_judge
    from models.eval.run import stylise

    inputs = _val(index, content, n=n, frames=150)
    outs = stylise(model, inputs, [model.styles().index("active")] * len(inputs))
    assert load_rotation_judge().predict_style([rotation_features(o) for o in outs]) == ["active"] * n
