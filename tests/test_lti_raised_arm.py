"""LTI: a raised hand that does not wave takes the real style's raised arm (`models/lti/raised_arm.py`):
only that arm moves, only while the hand is up and calm, the stream and the offline path agree,
and the validation raise-ups toward youthful read as raise-ups."""

from __future__ import annotations

import numpy as np
import pytest

from models.interface import FrameBatch
from models.lti import raised_arm
from models.lti.model import CARRY, WEIGHTS_DIR, LTIStyleModel
from models.motion.hands import clip_sway, hand_offsets, raise_share
from models.motion.rotations import quat_angle

from .lti_reference import carry_entry, unpacked
from .one_session import assert_lti_streams_as_offline, contents_read, stream, val_motions
from .reference.lti_offline import shares

pytestmark = pytest.mark.skipif(not (WEIGHTS_DIR / raised_arm.FILE).exists(), reason="LTI raised arm not committed")


@pytest.fixture(scope="module")
def models() -> tuple[LTIStyleModel, LTIStyleModel]:
    return LTIStyleModel(), LTIStyleModel(off=("raised_arm",))


def test_only_the_raised_calm_arm_moves_and_only_while_it_is_up(models, index):
    """A left-hand raise-up toward youthful: on the frames with the left hand up and calm only
    the left arm differs from the model without raised arms; before any hand goes up nothing does."""
    on, off = models
    motion = val_motions(index, "raise-up-left-hand")[0]
    pos = motion.global_positions()
    share = shares(hand_offsets(pos), clip_sway(hand_offsets(pos), motion.fps))
    got, before = stream(on, motion, "youthful")[0], stream(off, motion, "youthful")[0]
    moved = np.degrees(quat_angle(got, before))
    arm = [on.skeleton.index(f"{j}_L") for j in raised_arm.ARM_JOINTS]
    rest = [j for j in range(len(on.skeleton.names)) if j not in arm]
    up, down = share[:, 0] == 1.0, np.cumsum(raise_share(hand_offsets(pos)[..., 1]).max(-1)) == 0.0
    assert up.sum() >= 10 and down.sum() >= 5
    assert np.median(moved[up][:, arm].max(axis=-1)) > 2.0
    np.testing.assert_array_equal(got[:, rest], before[:, rest])  # the legs too: the planter sees the same
    np.testing.assert_array_equal(got[down], before[down])


def test_a_raise_up_streamed_equals_the_offline_path(models, index):
    """The numpy reference (`reference/lti_offline.py`) carries the raised arm as the stream does, frame by frame."""
    on, _ = models
    assert_lti_streams_as_offline(on, val_motions(index, "raise-up-right-hand")[0], "feminine")


def test_a_style_without_a_fit_streams_as_before(models, index):
    """An added style (an upload) has no raised arm: toward it the stream is what it was."""
    on, off = models
    import copy
    import dataclasses

    motion = val_motions(index, "raise-up-left-hand", frames=60)[0]
    with_added = copy.copy(on)
    with_added.add_style(dataclasses.replace(off.translators["youthful"], style="mine", raised_arm=None))
    np.testing.assert_array_equal(stream(with_added, motion, "mine")[0], stream(off, motion, "youthful")[0])


def test_a_snapshot_from_before_the_raised_arm_resumes(models, index):
    """A state without the hand keys (a replica before them) is upgraded: the sway starts again."""
    on, _ = models
    motion = val_motions(index, "raise-up-left-hand", frames=10)[0]
    state = on.init_state(1)
    w = np.zeros((1, len(on.styles())))
    w[0, 0] = 1.0
    for t in range(5):
        _, state = on.step_batch(state, FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1]), w)
    old = {k: v for k, v in unpacked(state).items() if not k.startswith("hand_")}
    upgraded = on.upgrade_state(old)
    assert not carry_entry(upgraded[CARRY], "hand_prev").any()
    out, state = on.step_batch(upgraded, FrameBatch(motion.translations[5:6, 1], motion.rotations[5:6]), w)
    assert np.isfinite(out.rotations).all() and carry_entry(state[CARRY], "hand_sway")[0].tolist() == [0.0, 0.0]


def test_validation_raise_ups_toward_youthful_read_as_raise_ups(models, index):
    """What it is for: without it the content judge read 2 of these 4 validation right-hand
    raise-ups toward youthful as waves (the hand 20-23 cm above the shoulder, the real youthful
    raise-ups' 42-45); with it at most one."""
    on, off = models
    read = contents_read((off, on), val_motions(index, "raise-up-right-hand", n=4), "youthful")
    assert sum(r == "raise-up-right-hand" for r in read[0]) == 2
    assert sum(r == "raise-up-right-hand" for r in read[1]) >= 3


def test_an_uploaded_style_is_fitted_the_same_way_from_its_clip(models, index, tmp_path):
    """`fit_styles` on one clip, as an upload gets it (`fit_upload`): a clip with a raised, calm
    left hand fits the left arm and leaves the right one as the translator makes it; a walk (no
    hand raised) fits nothing. The carry is saved with the uploaded translator and read back."""
    import copy

    _, off = models
    inputs = val_motions(index, "raise-up-left-hand", n=2) + val_motions(index, "raise-up-right-hand", n=2)
    raise_up = val_motions(index, "raise-up-left-hand", style="youthful", frames=400)[0]
    walk = val_motions(index, "walk", style="youthful")[0]
    carries = raised_arm.fit_styles(off, {"youthful": [raise_up]}, inputs)
    carry = carries["youthful"]
    assert carry is not None and raised_arm.fit_styles(off, {"youthful": [walk]}, inputs)["youthful"] is None
    left, right = raised_arm._ARM
    assert not np.allclose(carry.map[0, left], np.eye(3))  # fitted
    assert np.array_equal(carry.map[0, right], np.broadcast_to(np.eye(3), (len(right), 3, 3)))  # kept
    assert np.all(carry.radius[0, right] == np.pi)
    tr = copy.copy(off.translators["youthful"])
    tr.raised_arm = carry
    tr.save(tmp_path / "translator.npz")
    back = type(tr).load(tmp_path / "translator.npz").raised_arm
    assert back is not None and all(np.array_equal(a, b) for a, b in zip(back.arrays, carry.arrays))
