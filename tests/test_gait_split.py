"""`models.motion.gait_split`: a style's clips split into walks and runs by their own speeds."""

from __future__ import annotations

import math

import numpy as np

from models.motion.gait_split import MOVING_CM_S, run_threshold, running, two_groups


def test_two_groups_splits_between_them_and_one_group_is_not_split():
    assert two_groups([70, 80, 75, 140, 150, 145]) == 0.5 * (80 + 140)
    assert math.isinf(two_groups([100, 105, 110, 120]))  # less than SEPARATION apart: one group
    assert math.isinf(two_groups([100]))


def test_slow_runs_of_a_slow_style_are_runs_and_standing_clips_neither():
    """Elderly-like: walks at 0.6-0.8 m/s, runs at 1.3-1.5 m/s, slower than another style's walks;
    gestures stand (under `MOVING_CM_S`) and never count as walks or runs."""
    walks, runs, standing = [60.0, 70.0, 80.0], [130.0, 140.0, 150.0], [5.0, 10.0]
    speeds = walks + runs + standing
    assert all(s < MOVING_CM_S for s in standing)
    assert 80.0 < run_threshold(speeds) < 130.0
    np.testing.assert_array_equal(running(speeds), [False] * 3 + [True] * 3 + [False] * 2)
    assert not running(walks + standing).any()  # one gait: no run
