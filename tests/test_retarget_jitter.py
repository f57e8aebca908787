"""Retargeting adds no flips: per joint group, the p99 rotation acceleration of the retargeted BN
motion (and of a styled BN motion mapped back onto the client's rig) is at most
`retarget_check.BOUND` times the source's, on every CMU and Xia clip at the service's 30 fps and
on the made rigs (tests/rigs.py). Before the limb poles, CMU 131_02's right upper arm reached
162 deg/frame^2 and the Xia thighs 93-107, against 3-30 in the source; before the hips' rest side
and the spine's twist share, Xia's chest reached 1.7-2.1x the worst source spine joint; before the
learned hinge axis (`retarget.HINGE_FALLBACK`), the Xia punch's arms 1.7x onto BN and 1.4x back."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import load_motion, select
from models.motion.humanoid import humanoid_rig
from models.motion.retarget_stream import FrameRetargeter
from models.motion.rotations import quat_exp, quat_mul
from tools.retarget_check import BOUND, clip_jitter, group_ratios, rotation_acceleration

from .rigs import SPECS, make_rig

CLIPS = [
    ("cmu", "01_01"),
    ("cmu", "131_01"),
    ("cmu", "131_02"),
    ("cmu", "131_03"),
    ("xia", "angry_run_13_000"),
    ("xia", "depressed_punch_18_000"),
    ("xia", "depressed_run_13_000"),
    ("xia", "neutral_jump_16_000"),
    ("xia", "neutral_walk_01_000"),
    ("xia", "old_run_13_000"),
    ("xia", "sexy_walk_01_000"),
    ("xia", "sexy_walk_01_001"),
    ("xia", "strutting_walk_01_000"),
]
GROUPS = ("hips", "spine", "arms", "legs")


@pytest.fixture(scope="module")
def jitter(index) -> dict[str, dict[str, np.ndarray]]:
    return {name: clip_jitter(load_motion(select(index, dataset=ds, name=name)[0]), 30.0) for ds, name in CLIPS}


def test_every_clip_of_the_archives_is_listed(index):
    assert sorted((c.dataset, c.name) for c in index if c.dataset in ("cmu", "xia")) == sorted(CLIPS)


@pytest.mark.parametrize("name,group", [(n, g) for _, n in CLIPS for g in GROUPS])
def test_no_group_carries_more_jitter_than_the_source(jitter, name, group):
    j = jitter[name]
    assert group_ratios(j)[group] <= BOUND, j
    assert group_ratios(j, "back")[group] <= BOUND, j


def test_rotation_acceleration_sees_a_flip():
    """The measure itself: a steady turn has none; one frame turned by a half turn is a spike."""
    t = np.arange(40)[:, None, None]
    q = quat_exp(np.array([0.0, 0.05, 0.0]) * t)
    assert rotation_acceleration(q).max() < 1e-6
    flipped = q.copy()
    flipped[20] = quat_mul(flipped[20], quat_exp(np.array([np.pi * 0.9, 0.0, 0.0])))
    assert rotation_acceleration(flipped).max() > 150.0


@pytest.mark.parametrize("name", list(SPECS))
def test_made_rigs_round_trip_without_flips(bn_walk, name):
    """A BN walk on a made rig (other names, rest pose, twist bones, units, up axis): onto BN and a
    styled BN walk back, every group at most `BOUND` times the made rig's own jitter."""
    spec = SPECS[name]
    motion = make_rig(bn_walk.slice(0, 150), spec)
    rig = humanoid_rig(motion.skeleton, up=spec.up, translated=motion.skeleton.index(spec.rename["Hips"]))
    j = clip_jitter(motion, motion.fps, FrameRetargeter(rig))
    for key in ("bn", "back"):
        ratios = group_ratios(j, key)
        assert max(ratios.values()) <= BOUND, (key, ratios)
