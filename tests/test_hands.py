"""What a hand does (`models/motion/hands.py`): the compiled hand meter measures what the numpy
reference and the world positions give, and the sway tells a wave from a raise-up."""

from __future__ import annotations

import numpy as np

from models.motion.hands import (
    RAISE_RAMP_CM,
    SWAY_FRAMES,
    HandMeter,
    calm_frames,
    clip_sway,
    hand_offsets,
    wave_share,
)
from models.motion.hands_kernels import Hands, hand_step
from tests.reference.hands import clip_rise, hand_offsets_of, raised_frames

STILL_RAMP_CM_S = (25.0, 45.0)  # a hand is still below it, not above


def still_share(swayed: np.ndarray) -> np.ndarray:
    """(..., 2) how still each hand is: 1 up to `STILL_RAMP_CM_S`, 0 from its end, linear between."""
    lo, hi = STILL_RAMP_CM_S
    return 1.0 - np.clip((np.asarray(swayed, np.float64) - lo) / (hi - lo), 0.0, 1.0)


def meter_step(
    meter: HandMeter,
    rotations: np.ndarray,
    prev: np.ndarray,
    before: np.ndarray,
    rise_before: np.ndarray,
    started: np.ndarray,
    fps: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """((B, 2, 3) each hand's offset from its shoulder, (B, 2) its sway and (B, 2) its rise
    after this frame, whether any hand is on its raise ramp) from local rotations (B, J, 4),
    the previous frame's offsets `prev` and the averages `before` and `rise_before`, by the
    compiled meter as the LTI step runs it. A row has no previous frame unless `started`, nor
    while `prev` is all zeros (a state from before the meter); its averages start at 0."""
    q = np.ascontiguousarray(rotations, np.float64)
    out, swayed, risen = np.empty((len(q), 2, 3)), np.empty((len(q), 2)), np.empty((len(q), 2))
    arms = (meter.parents, meter.offsets, meter.chain, meter.hands, meter.shoulders)
    rig = Hands(*arms, float(fps), SWAY_FRAMES, RAISE_RAMP_CM[0])
    prev, before, rise_before = (np.ascontiguousarray(a, np.float64) for a in (prev, before, rise_before))
    raised = hand_step(q, rig, prev, before, rise_before, np.asarray(started, np.bool_), out, swayed, risen)
    return out, swayed, risen, bool(raised)


def _val(index, content: str):
    from models.data import load_motion, select

    return load_motion(select(index, dataset="bandai-namco-2", split="val", style="normal", content=content)[0])


def test_the_compiled_meter_measures_what_the_positions_give(index):
    """Frame by frame, as a stream calls it: the offsets are the world positions' (to round-off),
    the sway and the rise are `clip_sway`'s and `clip_rise`'s and the meter says so while a hand is on its raise ramp."""
    motion = _val(index, "wave-right-hand").slice(0, 120)
    meter = HandMeter(motion.skeleton)
    prev, swayed, risen = np.zeros((1, 2, 3)), np.zeros((1, 2)), np.zeros((1, 2))
    offsets, sways, rises, raised = [], [], [], []
    for t in range(motion.num_frames):
        prev, swayed, risen, up = meter_step(
            meter, motion.rotations[t : t + 1], prev, swayed, risen, np.array([t > 0]), motion.fps
        )
        offsets.append(prev[0])
        sways.append(swayed[0])
        rises.append(risen[0])
        raised.append(up)
    world = hand_offsets(motion.global_positions())
    np.testing.assert_allclose(np.array(offsets), world, atol=1e-3)  # the clip's positions are float32
    np.testing.assert_allclose(np.array(offsets), hand_offsets_of(motion.rotations, motion.skeleton), atol=1e-9)
    np.testing.assert_allclose(np.array(sways), clip_sway(np.array(offsets), motion.fps), atol=1e-9)
    np.testing.assert_allclose(np.array(rises), clip_rise(np.array(offsets), motion.fps), atol=1e-9)
    on_ramp = np.any(np.array(offsets)[..., 1] > RAISE_RAMP_CM[0], axis=-1)
    assert on_ramp.any() and not on_ramp.all()
    assert raised == list(on_ramp)


def test_a_state_from_before_the_meter_starts_its_sway_at_zero(index):
    """A started session whose previous offsets are all zeros (a snapshot from before the meter)
    has no previous frame: its sway restarts at 0 instead of a jump from the shoulder."""
    motion = _val(index, "wave-right-hand")
    meter = HandMeter(motion.skeleton)
    seven = np.full((1, 2), 7.0)
    _, swayed, risen, _ = meter_step(
        meter, motion.rotations[:1], np.zeros((1, 2, 3)), seven, seven, np.array([True]), 30.0
    )
    np.testing.assert_array_equal(swayed, 0.0)
    np.testing.assert_array_equal(risen, 0.0)


def test_a_waving_hand_sways_and_a_raised_one_holds_still(index):
    """On the frames with the right hand up, a validation wave's is waving and a raise-up's still."""
    for content, waving in (("wave-right-hand", True), ("raise-up-right-hand", False)):
        motion = _val(index, content).slice(0, 150)
        offsets = hand_offsets(motion.global_positions())
        swayed = clip_sway(offsets, motion.fps)[:, 1]
        up = offsets[:, 1, 1] > 0.0
        assert up.sum() >= 10
        assert np.median(wave_share(swayed[up])) == (1.0 if waving else 0.0)
        assert np.median(still_share(swayed[up])) == (0.0 if waving else 1.0)


def test_a_raise_ups_raised_frames_are_calm_and_a_waves_are_not(index):
    """`calm_frames` (what LTI's raised arm is fitted on): on the first validation one-hand
    raise-ups nearly every raised frame is calm, on the waves at most one in ten."""
    for side, hand in enumerate(("left", "right")):
        for content, calm in ((f"raise-up-{hand}-hand", True), (f"wave-{hand}-hand", False)):
            motion = _val(index, content).slice(0, 150)
            up = raised_frames(motion, side)
            assert up.sum() >= 20
            share = calm_frames(motion, side)[up].mean()
            assert share > 0.95 if calm else share <= 0.1
