"""The committed skeleton assets still match the data they were cut from."""

import numpy as np

from models.data import load_motion, select
from models.motion.assets import BANDAI_NAMCO_ANKLE_FLOOR, BANDAI_NAMCO_TOE_FLOOR, bandai_namco_pose, cmu_pose
from models.motion.retarget import Rig, contact_height


def test_bandai_namco_asset_is_the_first_frame_of_its_clip(index):
    clip = select(index, dataset="bandai-namco-2", name="dataset-2_walk_normal_001")[0]
    full = load_motion(clip)
    pose = bandai_namco_pose()
    assert pose.skeleton.names == full.skeleton.names
    np.testing.assert_allclose(pose.skeleton.offsets, full.skeleton.offsets, atol=1e-4)
    np.testing.assert_allclose(pose.global_positions()[0], full.global_positions()[0], atol=1e-3)
    assert abs(Rig.from_motion(full).floor - BANDAI_NAMCO_TOE_FLOOR) < 1e-3
    ankles = full.global_positions()[:, [full.skeleton.index("Foot_L"), full.skeleton.index("Foot_R")], 1]
    assert abs(contact_height(ankles) - BANDAI_NAMCO_ANKLE_FLOOR) < 1e-3


def test_cmu_asset_is_the_cmu_skeleton(index):
    full = load_motion(select(index, dataset="cmu", name="01_01")[0])
    assert cmu_pose().skeleton.names == full.skeleton.names
    np.testing.assert_allclose(cmu_pose().skeleton.offsets, full.skeleton.offsets, atol=1e-4)
