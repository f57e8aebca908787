"""Running sessions for the evaluation (`models/eval/history.py`): each scored clip comes after
seconds of other clips, joined without jumps, and is itself unchanged but for where it stands."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import load_motions
from models.eval.history import heading, with_history
from models.eval.run import pick_clips
from models.motion.rotations import quat_angle, quat_mul, wrap_angle, yaw_quat


@pytest.fixture(scope="module")
def clips():
    return [m.slice(0, 150) for m in load_motions(pick_clips(1, split="val"))]  # one per content


def _largest_joint_step_deg(motion) -> float:
    return float(np.degrees(quat_angle(motion.rotations[1:, 1:], motion.rotations[:-1, 1:])).max())


def _largest_hips_speed(motion) -> float:
    ground = motion.translations[:, 1, [0, 2]]
    return float((np.linalg.norm(np.diff(ground, axis=0), axis=1) * motion.fps).max())


def test_the_scored_clip_comes_after_the_history_asked_for(clips):
    for i in (0, 5):
        whole, start = with_history(clips, i, 300)
        assert start >= 300
        assert whole.num_frames - start == clips[i].num_frames


def test_the_scored_clip_is_itself_turned_and_moved_only(clips):
    i = 3
    whole, start = with_history(clips, i, 300)
    scored = whole.slice(start, whole.num_frames)
    clip = clips[i]
    assert np.array_equal(scored.rotations[:, 2:], clip.rotations[:, 2:])  # every joint below the hips
    turn = heading(scored, 0) - heading(clip, 0)
    turned = quat_mul(yaw_quat(np.full(clip.num_frames, turn)), clip.rotations[:, 1])
    assert np.degrees(quat_angle(scored.rotations[:, 1], turned)).max() < 0.1  # float32 clips
    assert np.allclose(scored.translations[:, 1, 1], clip.translations[:, 1, 1])  # heights
    path = np.linalg.norm(np.diff(scored.translations[:, 1, [0, 2]], axis=0), axis=1)
    assert np.allclose(path, np.linalg.norm(np.diff(clip.translations[:, 1, [0, 2]], axis=0), axis=1))


def test_the_history_joins_clips_without_a_jump_the_clips_do_not_have(clips):
    own_step = max(_largest_joint_step_deg(m) for m in clips)
    own_speed = max(_largest_hips_speed(m) for m in clips)
    for i in range(len(clips)):
        whole, start = with_history(clips, i, 300)
        assert _largest_joint_step_deg(whole) <= own_step + 1e-6
        assert _largest_hips_speed(whole) <= own_speed + 1e-6
        turns = np.abs(wrap_angle(np.diff([heading(whole, t) for t in range(start - 15, start + 2)])))
        assert np.degrees(turns).max() < 10.0  # facing on from the last clip into the scored one
