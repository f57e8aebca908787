"""The compiled per-frame retargeter (`retarget_kernels`, behind `FrameRetargeter.to_model` /
`to_source`) against its numpy reference (`tests/reference/retarget.py`): equal to
float round-off on made rigs (tests/rigs.py), on a CMU walk, on presets and on random poses, at
batch 1 and batched."""

from __future__ import annotations

import numpy as np
import pytest

from models.motion.humanoid import humanoid_rig, preset_rig
from models.motion.retarget_stream import FrameRetargeter

from .reference import retarget as reference
from .rigs import SPECS, make_rig

FRAMES = 60


def _qdiff(a: np.ndarray, b: np.ndarray) -> float:
    """Largest 1 - |cos(half angle)| between quaternions, up to sign (unmapped joints come back as
    sent, not necessarily unit length)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return float(np.abs(np.abs(np.sum(a * b, axis=-1)) - 1).max())


def _same(fr: FrameRetargeter, root: np.ndarray, rot: np.ndarray, new_hips: np.ndarray, new_rot: np.ndarray) -> None:
    """to_model and to_source (of the frames given and of other BN frames) equal the reference,
    batched and one frame at a time. Quaternions are compared up to sign (both give w >= 0; at
    w ~ 0 round-off may pick either)."""
    unit = fr.source.offsets.std() + 1.0  # translations compared relative to the rig's size
    hips, bn = fr.to_model(root, rot)
    ref_hips, ref_bn = reference.to_model(fr, root, rot)
    np.testing.assert_allclose(hips / unit, ref_hips / unit, atol=1e-9)
    assert _qdiff(bn, ref_bn) < 1e-9
    assert np.abs(bn - ref_bn).max() < 1e-6  # and the same sign
    for bn_root, bn_rot in ((hips, bn), (new_hips, new_rot)):
        back_root, back_rot = fr.to_source(bn_root, bn_rot, rot)
        ref_root, ref_rot = reference.to_source(fr, bn_root, bn_rot, rot)
        np.testing.assert_allclose(back_root / unit, ref_root / unit, atol=1e-9)
        assert _qdiff(back_rot, ref_rot) < 1e-9
        assert np.abs(back_rot - ref_rot).max() < 1e-6
    for f in (0, len(root) // 2, len(root) - 1):  # batch 1 with the stream's state, as the service calls it
        state = fr.init_state()
        fr.to_model(root[:f], rot[:f], state)
        ref_state = state.copy()
        h1, b1 = fr.to_model(root[f], rot[f], state)
        np.testing.assert_allclose(h1[0], hips[f], rtol=0, atol=1e-9 * unit)
        np.testing.assert_allclose(b1[0], bn[f], atol=1e-12)
        reference.to_model(fr, root[f], rot[f], ref_state)
        np.testing.assert_allclose(state, ref_state, rtol=1e-9, atol=1e-12)
        r1, q1 = fr.to_source(new_hips[f], new_rot[f], rot[f], state)
        r2, q2 = reference.to_source(fr, new_hips[f][None], new_rot[f][None], rot[f][None], ref_state)
        np.testing.assert_allclose(r1 / unit, r2 / unit, atol=1e-9)
        assert _qdiff(q1, q2) < 1e-9


@pytest.fixture(scope="module")
def walk(bn_walk):
    return bn_walk.slice(0, FRAMES)


@pytest.fixture(scope="module")
def bn_frames(walk):
    """BN frames from later in the walk (what a style would send back)."""
    fr = FrameRetargeter(humanoid_rig(walk.skeleton, translated=walk.skeleton.index("Hips")))
    return reference.to_model(fr, walk.translations[::-1, 1], walk.rotations[::-1])


@pytest.mark.parametrize("name", list(SPECS))
def test_kernel_equals_numpy_on_made_rigs(walk, bn_frames, name):
    spec = SPECS[name]
    motion = make_rig(walk, spec)
    rig = humanoid_rig(motion.skeleton, up=spec.up, translated=motion.skeleton.index(spec.rename["Hips"]))
    fr = FrameRetargeter(rig)
    _same(fr, motion.translations[:, fr.humanoid.translated], motion.rotations, *bn_frames)


def test_kernel_equals_numpy_on_a_cmu_walk(cmu_walk, bn_frames):
    motion = cmu_walk.slice(0, FRAMES)
    fr = FrameRetargeter(motion.skeleton)
    assert fr.humanoid.preset is not None and fr.humanoid.preset.startswith("cmu")
    _same(fr, motion.translations[:, fr.humanoid.translated], motion.rotations, *bn_frames)


@pytest.mark.parametrize("preset", ["ue5", "mixamo", "cmu", "smpl"])
def test_kernel_equals_numpy_on_random_poses(bn_frames, preset):
    """Far from any walk: random client rotations (not unit length), a root joint above the hips."""
    fr = FrameRetargeter(preset_rig(preset))
    rng = np.random.default_rng(1)
    rot = rng.normal(size=(FRAMES, fr.source.num_joints, 4)) * 0.5 + [0, 0, 0, 2.0]
    root = rng.normal(size=(FRAMES, 3)) * 50
    _same(fr, root, rot, *bn_frames)


def test_float32_frames_and_bad_shapes():
    fr = FrameRetargeter(preset_rig("mixamo"))
    rng = np.random.default_rng(2)
    rot = (rng.normal(size=(fr.source.num_joints, 4)) * 0.2 + [0, 0, 0, 1]).astype(np.float32)
    root = np.array([1.0, 90.0, 3.0], np.float32)
    hips, bn = fr.to_model(root, rot)
    ref_hips, ref_bn = reference.to_model(fr, root, rot)
    np.testing.assert_allclose(hips, ref_hips, atol=1e-9)
    np.testing.assert_allclose(bn, ref_bn, atol=1e-12)
    with pytest.raises(ValueError, match="client joints"):
        fr.to_model(root, rot[:-1])
    with pytest.raises(ValueError, match="client joints"):
        fr.to_source(hips, bn, rot[:-1])
