"""The packed LPN training set (`models/lpn/carry.py`): a mirror image rebuilt by reflecting its
take's frames must be the mirror image the cache computes from the mirrored motion, and a sample
rebuilt from frames must be the one `clip_samples` gives."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motion, select
from models.lpn.carry import mirror_frames
from models.lpn.dataset import clip_frames, clip_samples, samples_from_frames
from models.motion.features import mirror


@pytest.fixture(scope="module")
def turn():
    index = build_index(["bandai-namco-2"])
    return load_motion(select(index, split="val", style="active", content="walk-turn-left")[0])


def test_a_reflected_take_is_the_mirrored_motions_frames(turn):
    own, want = clip_frames(turn), clip_frames(mirror(turn))
    got = mirror_frames(own, want.phases, want.frequency, want.contacts)
    assert np.allclose(got.xz, want.xz, atol=1e-3)
    assert np.allclose(np.sin(got.yaw - want.yaw), 0.0, atol=1e-5)
    # every channel of every body joint: position, velocity (cm, cm/s), forward and up axes
    assert np.abs(got.pose - want.pose).max() < 1e-2


def test_samples_from_frames_are_the_clips_samples(turn):
    want = clip_samples(turn, gait=0.0)
    got = samples_from_frames(clip_frames(turn), gait=0.0)
    for key in ("X", "G", "Y", "style_feats"):
        assert np.array_equal(getattr(got, key), getattr(want, key)), key
