"""A capture that carries its travel on a joint above the hips (4 of dataset 1's neutral clips move
`joint_Root`, the model rig's static root) is read with the travel on the hips, where every model,
the service and the evaluation take the body's travel: read as it was, the models saw a walk in
place and the travel came back under the planted feet."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.data import load_motion, select
from models.motion import bvh as bvhio
from models.motion.assets import bandai_namco_skeleton
from models.motion.bn_skeleton import HIPS, ROOT
from models.motion.skeleton import from_bvh, travel_on


@pytest.fixture(scope="module")
def walk_on_root(index):
    clip = next(
        c for c in select(index, dataset="bandai-namco-1", style="normal") if c.name == "dataset-1_walk_normal_002"
    )
    return clip, from_bvh(bvhio.read(clip.path))


def test_the_file_moves_its_root_joint_and_the_loader_moves_it_onto_the_hips(walk_on_root):
    clip, raw = walk_on_root
    assert np.ptp(raw.translations[:, ROOT, 2]) > 150.0 and np.ptp(raw.translations[:, HIPS, 2]) < 10.0
    loaded = load_motion(clip)
    assert np.ptp(loaded.translations[:, ROOT], axis=0).max() == 0.0
    assert np.ptp(loaded.translations[:, HIPS, 2]) > 150.0
    # the same world pose of every body joint
    np.testing.assert_allclose(loaded.global_positions()[:, 1:], raw.global_positions()[:, 1:], atol=1e-3)


def test_a_rotating_root_joint_folds_into_the_hips_too(walk_on_root):
    _, raw = walk_on_root
    turned = raw.rotations.copy()
    angle = np.linspace(0.0, 1.5, raw.num_frames)
    turned[:, ROOT] = np.stack([np.zeros_like(angle), np.sin(angle / 2), np.zeros_like(angle), np.cos(angle / 2)], -1)
    moving = type(raw)(raw.skeleton, turned, raw.translations, raw.fps, raw.euler_orders)
    folded = travel_on(moving, HIPS)
    assert np.allclose(folded.rotations[:, ROOT], folded.rotations[:1, ROOT])
    np.testing.assert_allclose(folded.global_positions()[:, 1:], moving.global_positions()[:, 1:], atol=1e-6)


def test_a_clip_that_travels_on_its_hips_is_left_as_it_is(index):
    clip = select(index, dataset="bandai-namco-2", style="normal", content="walk")[0]
    raw = from_bvh(bvhio.read(clip.path))
    assert travel_on(raw, HIPS) is raw


def test_an_uploaded_bvh_keeps_its_travel(walk_on_root):
    from service.clips import motion_from_bvh

    clip, _ = walk_on_root
    motion, rig = motion_from_bvh(Path(clip.path).read_text(), bandai_namco_skeleton())
    assert rig == "bandai-namco"
    assert np.ptp(motion.translations[:, HIPS, 2]) > 150.0


def test_a_rig_whose_root_joint_travels_keeps_its_travel_through_the_retargeter(walk_on_root):
    """Root and hips both with position channels, the travel on the root (as game rigs export root
    motion): retargeted, the model rig's hips travel as the file's do."""
    from models.motion.humanoid import rig_from_bvh
    from models.motion.retarget import retarget

    clip, raw = walk_on_root
    rig = rig_from_bvh(Path(clip.path).read_text())  # frames carry the hips (they have position channels)
    assert raw.skeleton.names[rig.translated] == "Hips"
    out = retarget(raw, fps=raw.fps, source=rig)
    travel = np.ptp(raw.global_positions()[:, HIPS, 2])
    assert travel > 150.0
    assert np.ptp(out.translations[:, HIPS, 2]) == pytest.approx(travel, rel=0.05)
