"""What a hand does (`models/motion/hands.py`): the compiled hand meter measures what the numpy
reference and the world positions give, and the sway tells a wave from a raise-up."""

from __future__ import annotations

import numpy as np

from models.motion.hands import HandMeter, clip_sway, hand_offsets, hand_offsets_of, still_share, wave_share


def _val(index, content: str):
    from models.data import load_motion, select

    return load_motion(select(index, dataset="bandai-namco-2", split="val", style="normal", content=content)[0])


def test_the_compiled_meter_measures_what_the_positions_give(index):
    """Frame by frame, as a stream calls it: the offsets are the world positions' (to round-off)
    and the sway is `clip_sway`'s."""
    motion = _val(index, "wave-right-hand").slice(0, 120)
    meter = HandMeter(motion.skeleton)
    prev, swayed = np.zeros((1, 2, 3)), np.zeros((1, 2))
    offsets, sways = [], []
    for t in range(motion.num_frames):
        prev, swayed = meter.step(motion.rotations[t : t + 1], prev, swayed, np.array([t > 0]), motion.fps)
        offsets.append(prev[0])
        sways.append(swayed[0])
    world = hand_offsets(motion.global_positions())
    np.testing.assert_allclose(np.array(offsets), world, atol=1e-3)  # the clip's positions are float32
    np.testing.assert_allclose(np.array(offsets), hand_offsets_of(motion.rotations, motion.skeleton), atol=1e-9)
    np.testing.assert_allclose(np.array(sways), clip_sway(np.array(offsets), motion.fps), atol=1e-9)


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
