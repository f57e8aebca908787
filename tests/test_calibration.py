"""Another performer's posture is turned into the model's range before it styles a frame, and
back after (`models/motion/calibration.py`): on a real dataset-1 walk, whose clavicles sit
outside every dataset-2 clip's, without touching the models' own performer."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import load_motion, select
from models.interface import FrameBatch, style_vector
from models.motion.bn_skeleton import BN_JOINTS, HIPS
from models.motion.calibration import KEY, PostureRange, reference_path
from models.registry import load_model
from models.settings import get_settings

WEIGHTS = get_settings().weights_dir
CLAVICLES = [BN_JOINTS.index(n) for n in ("Shoulder_L", "Shoulder_R")]


@pytest.fixture(scope="module")
def d1_walk(index):
    return load_motion(select(index, dataset="bandai-namco-1", style="normal", content="walk")[0])


@pytest.fixture(scope="module")
def posture():
    return PostureRange.load(reference_path(WEIGHTS, "erd"))


def test_a_dataset_1_walk_has_its_clavicles_turned_into_range(d1_walk, posture):
    turns = np.degrees(posture.settled_turns(d1_walk.rotations, d1_walk.fps))
    assert all(turns[j] > 10.0 for j in CLAVICLES), turns[CLAVICLES]


def test_the_models_own_performer_is_left_as_it_is(index, posture):
    """A held-out dataset-2 walk lies in the range of the model's clips: no joint turns more
    than a few degrees."""
    walk = load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])
    assert np.degrees(posture.settled_turns(walk.rotations, walk.fps)).max() < 6.0


def test_the_output_turned_back_is_the_input_when_the_model_changes_nothing(d1_walk, posture):
    state = posture.init_state(1)
    for frame in d1_walk.rotations[:90].astype(np.float64):
        frame = frame / np.linalg.norm(frame, axis=-1, keepdims=True)
        back = posture.restore(posture.calibrate(frame[None], state, d1_walk.fps), state)[0]
        np.testing.assert_allclose(np.abs(np.sum(back * frame, axis=-1)), 1.0, atol=1e-9)


def test_calibrated_the_walk_lies_where_lti_was_identified(d1_walk, posture):
    """LTI hands back every frame with an input DOF outside its training range (its erf blend):
    a dataset-1 walk's clavicles are, on every frame; calibrated (the same neutral clips fit
    both), few frames are."""
    from dataclasses import replace

    from models.lti import representation as rep

    lti = load_model(WEIGHTS, "lti", core_only=True).translators["elderly"]
    calibrated, _ = posture.clip(d1_walk.rotations, d1_walk.fps)
    settled = int(2 * d1_walk.fps)
    handed_back = {}
    for name, rotations in (("raw", d1_walk.rotations), ("calibrated", calibrated)):
        feats = rep.motion_to_features(replace(d1_walk, rotations=rotations), lti.ref)[settled:]
        handed_back[name] = float(np.mean(lti.blend_weight((feats - lti.in_mean) / lti.in_std) > 0.5))
    assert handed_back["raw"] > 0.9 and handed_back["calibrated"] < 0.4, handed_back


def test_shipped_sessions_are_calibrated_and_cores_are_not():
    assert KEY in load_model(WEIGHTS, "erd").init_state(1)
    assert KEY not in load_model(WEIGHTS, "erd", core_only=True).init_state(1)
    assert KEY not in load_model(WEIGHTS, "erd", calibration=False).init_state(1)


def test_a_session_is_calibrated_alone_whatever_its_batch(d1_walk, index):
    """Two sessions stepped together get what each gets alone: the turns are per session."""
    model = load_model(WEIGHTS, "erd")
    d2 = load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk")[0])
    clips = [d1_walk, d2]
    weights = np.stack([style_vector(model, {"elderly": 1.0})] * 2)
    together, alone = model.init_state(2), [model.init_state(1) for _ in clips]
    for t in range(60):
        root = np.stack([m.translations[t, HIPS] for m in clips])
        rot = np.stack([m.rotations[t] for m in clips]).astype(np.float64)
        out, together = model.step_batch(together, FrameBatch(root, rot), weights)
        for i in range(2):
            one, alone[i] = model.step_batch(alone[i], FrameBatch(root[i : i + 1], rot[i : i + 1]), weights[i : i + 1])
            np.testing.assert_allclose(out.rotations[i], one.rotations[0], atol=1e-6)
    assert not np.allclose(together[KEY][0], together[KEY][1])


def test_no_hinge_is_turned_past_its_floor_on_another_performers_walks(index):
    """The hinge joints are never turned: turned back after the model held them at their floor,
    a dataset-1 elbow came out bent 4 degrees backwards. Every style, both dataset-1 walks."""
    from models.motion.hinge import Hinges
    from models.motion.rotations import quat_log, swing_twist
    from models.motion.twist import bone_axes

    model = load_model(WEIGHTS, "erd")
    hinges = Hinges.load(WEIGHTS / "erd" / "hinge_floor.npz")
    styles = model.styles()
    weights = np.stack([style_vector(model, {s: 1.0}) for s in styles])
    for clip in select(index, dataset="bandai-namco-1", style="normal", content="walk"):
        walk = load_motion(clip)
        axes = bone_axes(walk.skeleton)
        state = model.init_state(len(styles))
        for t in range(walk.num_frames):
            root = np.repeat(walk.translations[t : t + 1, HIPS], len(styles), axis=0).astype(np.float64)
            rot = np.repeat(walk.rotations[t : t + 1], len(styles), axis=0).astype(np.float64)
            out, state = model.step_batch(state, FrameBatch(root, rot), weights)
            q = out.rotations / np.linalg.norm(out.rotations, axis=-1, keepdims=True)
            for j, axis, floor in zip(hinges.joints, hinges.axes, hinges.floor):
                bend = quat_log(swing_twist(q[:, j], axes[j])[0]) @ axis
                assert np.degrees(bend - floor).min() > -1.0, (clip.name, t, BN_JOINTS[j])
