"""Unseen content is kept: every shipped model fades toward the input on a crouch it never saw
(`models/motion/novelty.py`), comes back after, and leaves a neutral walk of its own data alone."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import load_motion, select
from models.interface import FrameBatch, style_vector
from models.motion.bn_skeleton import BN_JOINTS, HIPS, ROOT
from models.motion.novelty import (
    FADED,
    LIFT_FULL,
    NoveltyReference,
    body_parts,
    reference_path,
    smooth,
)
from models.motion.novelty_kernels import KIND_LEG_END, W1, fade_step
from models.motion.novelty_stage import KEY, KEYS, faded, fresh_state
from models.motion.retarget import retarget
from models.motion.rotations import quat_angle, quat_exp, quat_inv, quat_log, quat_mul
from models.motion.skeleton import fk
from models.registry import METHODS, load_model, load_models
from models.settings import get_settings

from .pick_up import pick_up

WEIGHTS = get_settings().weights_dir


@pytest.fixture(scope="module")
def crouch(index):
    """A Xia walk that stops to crouch and pick something up (on the model rig at 30 fps), the
    seconds it is fully down, and when its legs are back in the walk's pose."""
    made = pick_up(load_motion(select(index, dataset="xia", name="neutral_walk_01_000")[0]), walk_s=1.0)
    return retarget(made.motion), made.down, made.crouch[1]


def test_parts_cover_the_body_once():
    from models.motion.assets import bandai_namco_skeleton

    parts = body_parts(bandai_namco_skeleton().parents)
    names = [[BN_JOINTS[j] for j in p] for p in parts]
    joined = sorted(j for p in parts for j in p)
    assert joined == [j for j in range(len(BN_JOINTS)) if j != ROOT]
    assert names[0][0] == "Hips" and "Toes_L" in names[0] and "Toes_R" in names[0]
    assert names[1] == ["Spine", "Chest", "Neck", "Head"]
    assert sorted(len(p) for p in names[2:]) == [4, 4]  # one part per arm


def test_features_come_from_the_chain_ends():
    """The head and each hand by position, each leg's end by reach and height: nothing else."""
    from models.motion.assets import bandai_namco_skeleton
    from models.motion.novelty import feature_kinds
    from models.motion.novelty_kernels import KIND_POSITION

    ref = NoveltyReference.load(reference_path(WEIGHTS, "lti"))
    kind, root = feature_kinds(bandai_namco_skeleton().parents, ref.part)
    named = {BN_JOINTS[j]: int(k) for j, k in enumerate(kind) if k}
    ends = {"Head": KIND_POSITION, "Hand_L": KIND_POSITION, "Hand_R": KIND_POSITION}
    assert named == {**ends, "Toes_L": KIND_LEG_END, "Toes_R": KIND_LEG_END}
    assert {BN_JOINTS[int(root[BN_JOINTS.index(f"Toes_{s}")])] for s in "LR"} == {"UpperLeg_L", "UpperLeg_R"}


def test_the_fade_rises_and_falls_without_a_step():
    w1 = w2 = np.zeros(1)
    trace = []
    for t in range(80):
        w1, w2 = smooth(w1, w2, np.array([1.0 if 10 <= t < 40 else 0.0]))
        trace.append(float(w2[0]))
    w = np.array(trace)
    assert w[:10].max() == 0.0 and w[30] > 0.95 and w[79] < 0.05
    assert np.all(np.diff(w[10:40]) >= 0) and np.all(np.diff(w[40:]) <= 0)
    assert np.abs(np.diff(w, 2)).max() < 0.15  # its rate changes by little each frame: no pop


def _blend(out: np.ndarray, inp: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The numpy reference of the compiled blend: slerp along the shorter arc, by w (B, J)."""
    rel = quat_mul(quat_inv(out), inp)
    rel = np.where(rel[..., 3:] < 0.0, -rel, rel)
    return np.where(w[..., None] > 0.0, quat_mul(out, quat_exp(w[..., None] * quat_log(rel))), out)


def _lowest_foot(ref: NoveltyReference, rot: np.ndarray) -> float:
    """The numpy reference of the compiled lowest foot point: each leg end and the joint above
    it, from the hips, for local rotations (J, 4)."""
    q = rot[None].copy()
    q[:, ROOT] = (0.0, 0.0, 0.0, 1.0)
    bones = ref.bones[None].copy()
    bones[:, [ROOT, HIPS]] = 0.0
    pos = fk(q, bones, ref.parents)[1][0]
    ends = np.flatnonzero(ref.kinds[0] == KIND_LEG_END)
    return float(pos[np.r_[ends, ref.parents[ends]], 1].min())


def _outputs(batch: int, joints: int, state: np.ndarray) -> tuple[np.ndarray, ...]:
    """What `fade_step` writes into, filled with garbage: it must overwrite every entry."""
    return tuple(np.full(s, np.nan) for s in ((batch, joints, 4), (batch, 3), state.shape, (batch,)))


def test_the_compiled_step_is_the_numpy_reference(crouch):
    """`fade_step` frame by frame gives the fades `clip_fades` computes over the whole clip and
    the numpy slerp and lerp toward the input; at fade 0 the output is the method's, exactly."""
    motion = crouch[0]
    ref = NoveltyReference.load(reference_path(WEIGHTS, "lti"))
    rng = np.random.default_rng(0)
    rot = motion.rotations.astype(np.float64)
    root = motion.translations[:, HIPS].astype(np.float64)
    method_rot = quat_mul(rot, quat_exp(0.3 * rng.normal(size=(1, rot.shape[1], 3))))  # a "style"
    method_root = root + (5.0, -3.0, 2.0) + np.arange(len(root))[:, None] * (1.0, 0.0, 0.0)  # it walks on
    want = ref.clip_fades(rot, root[:, 1], motion.fps)
    state = fresh_state(1, ref.parts)[KEY]
    ground, lifts = np.zeros(3), []  # the reference's offset across the ground, its lifts
    for t in range(len(rot)):
        before, prev = state.copy(), state
        out_rot, out_root, state, fade = _outputs(1, rot.shape[1], prev)
        fade_step(
            rot[t : t + 1], root[t : t + 1], method_rot[t : t + 1], method_root[t : t + 1], np.zeros((0, 5)),
            prev, ref.arrays(motion.fps), out_rot, out_root, state, fade,
        )  # fmt: skip
        np.testing.assert_array_equal(prev, before)  # the state passed in is left as it was (snapshots)
        parts = faded({KEY: state})
        np.testing.assert_allclose(fade, parts, atol=0.0)
        np.testing.assert_allclose(fade[0], want[t].max(), atol=1e-9)
        joint = np.where(ref.part >= 0, want[t : t + 1][:, np.maximum(ref.part, 0)], 0.0)  # each joint's part's fade
        assert quat_angle(out_rot, _blend(method_rot[t : t + 1], rot[t : t + 1], joint)).max() < 1e-6
        w = joint[0, HIPS]
        if t > 0:
            ground[[0, 2]] += w * ((root[t] - root[t - 1]) - (method_root[t] - method_root[t - 1]))[[0, 2]]
        want_root = method_root[t] + ground
        want_root[1] = method_root[t, 1] + w * (root[t, 1] - method_root[t, 1])
        x = min(max(w, state[0, W1 * ref.parts + ref.part[HIPS]]) / LIFT_FULL, 1.0)
        sink = root[t, 1] + _lowest_foot(ref, rot[t]) - (want_root[1] + _lowest_foot(ref, out_rot[0]))
        lifted = x * x * (3.0 - 2.0 * x) * max(sink, 0.0)
        want_root[1] += lifted
        lifts.append(lifted)
        np.testing.assert_allclose(out_root[0], want_root, atol=1e-9)
        if fade.max() == 0.0:
            np.testing.assert_array_equal(out_rot, method_rot[t : t + 1])
    assert ground[0] < -10.0  # fully faded, the output stopped walking with the input
    assert max(lifts) > 1.0  # the blend of the "style" and the crouch sank, and the root rose
    assert want.max() > 0.99  # the clip went through the whole fade


def test_a_controller_tick_keeps_nothing():
    """A row whose control flag is set has no pose to keep: its output is the method's."""
    ref = NoveltyReference.load(reference_path(WEIGHTS, "lpn"))
    rng = np.random.default_rng(1)
    rot = quat_exp(rng.normal(size=(2, len(BN_JOINTS), 3)))  # far from any training pose
    root, method = np.tile([0.0, 20.0, 0.0], (2, 1)), quat_exp(0.1 * rng.normal(size=(2, len(BN_JOINTS), 3)))
    control = np.zeros((2, 5))
    control[1, 4] = 1.0
    state = fresh_state(2, ref.parts)[KEY]
    for _ in range(20):
        prev = state
        out_rot, out_root, state, fade = _outputs(2, len(BN_JOINTS), prev)
        fade_step(rot, root, method, root, control, prev, ref.arrays(30.0), out_rot, out_root, state, fade)
    assert fade[0] > 0.9 and fade[1] == 0.0
    np.testing.assert_array_equal(out_rot[1], method[1])


@pytest.mark.parametrize("method", METHODS)
def test_every_reference_fades_on_the_crouch_and_not_after(method, crouch):
    motion, down, back = crouch
    ref = NoveltyReference.load(reference_path(WEIGHTS, method))
    lower = ref.clip_fades(motion.rotations, motion.translations[:, HIPS, 1], motion.fps)[:, 0]
    t = np.arange(len(lower)) / motion.fps
    assert lower[(t > down[0] + 0.3) & (t < down[1])].min() > FADED, method
    assert lower[t > back + 0.8].max() < 0.1, method
    assert lower[t < down[0] - 0.6].max() < 0.1, method


@pytest.mark.parametrize("method", METHODS)
def test_another_performers_walks_hardly_fade(method, index):
    """Xia's walks (validation inputs of the evaluation), retargeted: another performer and rig."""
    ref = NoveltyReference.load(reference_path(WEIGHTS, method))
    clips = [c for c in select(index, dataset="xia", content="walk") if c.split == "train"]
    assert len(clips) >= 3
    for clip in clips:
        walk = retarget(load_motion(clip))
        w = ref.clip_fades(walk.rotations, walk.translations[:, HIPS, 1], walk.fps).max(axis=1)
        assert np.mean(w > FADED) < 0.05, (method, clip.name)


@pytest.mark.parametrize("method", METHODS)
def test_the_feet_stay_on_the_inputs_floor_through_the_pick_up(method, index):
    """Every shipped model, through the streaming interface: from the walk into the crouch and out
    of it, the output's lowest foot point stays within 4 cm of the input's (without the fade
    the models sink up to 25 cm into the floor; what is left is Style-ERD's own 3-4 cm as the
    knees start to bend, before the input is far from a walk)."""
    from models.eval.run import stylise_toward

    made = pick_up(load_motion(select(index, dataset="xia", name="neutral_walk_01_000")[0]), walk_s=1.0)
    motion = retarget(made.motion)
    out = stylise_toward(load_model(WEIGHTS, method), [motion], ["elderly"])["elderly"][0]
    feet = [BN_JOINTS.index(f"{p}_{s}") for p in ("Foot", "Toes") for s in "LR"]
    low_in, low_out = (m.global_positions()[:, feet, 1].min(axis=1) for m in (motion, out))
    t = np.arange(motion.num_frames) / motion.fps
    inside = (t >= made.crouch[0]) & (t <= made.crouch[1] + 0.5)
    assert (low_out - low_in)[inside].min() > -4.0, method


@pytest.mark.parametrize("method", ("lti", "erd"))
def test_a_neutral_walk_of_the_training_data_hardly_fades(method, bn_walk):
    ref = NoveltyReference.load(reference_path(WEIGHTS, method))
    w = ref.clip_fades(bn_walk.rotations, bn_walk.translations[:, HIPS, 1], bn_walk.fps).max(axis=1)
    assert np.mean(w > FADED) < 0.02, method


def test_the_shipped_model_keeps_the_crouch_and_its_style_after(crouch):
    """Through the streaming interface: faded frames carry the input's legs and root height, the
    frames long after carry the style again, and the state survives an upgrade. The feet are
    planted after the fade, so a held foot may turn the legs a few degrees off the input's: it
    stays where it stood instead of sliding to where the input's leg would put it."""
    motion, down, back = crouch
    model = load_model(WEIGHTS, "lti")
    weights = style_vector(model, {"elderly": 1.0})[None]
    state = model.init_state(1)
    assert set(KEYS) <= set(state)
    assert model.upgrade_state(state) is state
    legs = [BN_JOINTS.index(n) for n in ("UpperLeg_L", "LowerLeg_L", "UpperLeg_R", "LowerLeg_R")]
    t_down = int((down[0] + down[1]) / 2 * motion.fps)
    t_after = motion.num_frames - 1
    for t in range(t_after + 1):
        frame = FrameBatch(motion.translations[t : t + 1, HIPS], motion.rotations[t : t + 1])
        out, state = model.step_batch(state, frame, weights)
        if t == t_down:
            assert out.faded[0] > 0.9 and faded(state)[0] == out.faded[0]
            assert quat_angle(out.rotations[0, legs], motion.rotations[t, legs]).max() < np.radians(10)
            assert abs(out.root[0, 1] - motion.translations[t, HIPS, 1]) < 2.0  # cm
    assert out.faded[0] < 0.05
    assert quat_angle(out.rotations[0, 1:], motion.rotations[t_after, 1:]).max() > np.radians(3)  # styled again


def test_an_old_snapshot_gets_a_fresh_fade():
    model = load_model(WEIGHTS, "lti")
    old = {k: v for k, v in model.init_state(2).items() if k not in KEYS}
    upgraded = model.upgrade_state(old)
    assert set(KEYS) <= set(upgraded) and faded(upgraded).shape == (2,) and not faded(upgraded).any()


def test_the_core_has_no_fade():
    core = load_model(WEIGHTS, "lti", core_only=True)
    assert not any(k in core.init_state(1) for k in KEYS)


def test_the_service_can_switch_the_fade_off():
    """`STYLESTREAM_UNSEEN_FADE=false` loads the shipped pipelines without their last stage."""
    from service.settings import ServiceSettings

    assert ServiceSettings().unseen_fade and not ServiceSettings(unseen_fade=False).unseen_fade
    shipped = load_models(WEIGHTS)["lti"].init_state(1)
    without = load_models(WEIGHTS, novelty=False)["lti"].init_state(1)
    assert all(k in shipped for k in KEYS) and not any(k in without for k in KEYS)


def test_lti_fading_inside_its_step_is_the_stage(crouch):
    """LTI runs the fade inside its own compiled step (`step_batch_fading`), before its feet are
    pitched and planted: through the crouch, for a style and a mix with an intensity below 1, it
    gives what the stage gives after LTI's step without its feet, pitched and planted after, to the bit."""
    from models.lti import LTIStyleModel
    from models.motion.feet import STATE_SHAPES
    from models.motion.feet_kernels import PITCH_SHARE, Feet, follow_pitch
    from models.motion.novelty_stage import with_novelty

    motion, _, _ = crouch
    fused = load_model(WEIGHTS, "lti")

    class Separate(LTIStyleModel):
        step_batch_fading = None  # the stage's own fade (`fade_step` called from Python)

    separate = with_novelty(Separate(footlock=False, off=("foot_pitch",)), fused.novelty)
    planter = fused.planter
    weights = np.stack([style_vector(fused, {"elderly": 1.0}), style_vector(fused, {"feminine": 0.5, "active": 0.3})])
    state, separate_state, feet = fused.init_state(2), separate.init_state(2), planter.init_state(2)
    seen = 0.0
    for t in range(motion.num_frames):
        frame = FrameBatch(
            np.repeat(motion.translations[t : t + 1, HIPS], 2, 0), np.repeat(motion.rotations[t : t + 1], 2, 0)
        )
        a, state = fused.step_batch(state, frame, weights)
        b, separate_state = separate.step_batch(separate_state, frame, weights)
        pitched, before = b.rotations.copy(), Feet(*(feet[k].astype(d) for k, (_, d) in STATE_SHAPES.items()))
        follow_pitch(frame.rotations, pitched, b.root, before, planter._params, PITCH_SHARE)
        root, rotations, contacts, feet = planter(feet, b.root, pitched, hints=b.contacts)
        for got, want in ((a.rotations, rotations), (a.root, root), (a.faded, b.faded), (a.contacts, contacts)):
            np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(state[KEY], separate_state[KEY])
        seen = max(seen, float(a.faded.max()))
    assert seen > 0.9  # the crouch faded


@pytest.mark.parametrize("method, before_feet", [("erd", True), ("lpn", False)])
def test_each_method_fades_where_it_declares_before_or_after_its_feet(crouch, method, before_feet):
    """Through the crouch: Style-ERD's fade runs between its step and its planted feet, LPN-FiLM's
    after its whole step (`fade_before_feet`, chosen on validation): each equals that order
    composed by hand, to the bit, and the two orders differ once the fade rises."""
    from models.motion.feet import plant_frame
    from models.motion.novelty_stage import FadesUnseen

    motion, _, _ = crouch
    model = load_model(WEIGHTS, method, calibration=False)
    assert getattr(model, "fade_before_feet", True) is before_feet
    weights = style_vector(model, {"elderly": 1.0})[None]
    state, mine = model.init_state(1), model.init_state(1)
    differs = False
    for t in range(motion.num_frames):
        frame = FrameBatch(motion.translations[t : t + 1, HIPS], motion.rotations[t : t + 1])
        got, state = model.step_batch(state, frame, weights)
        out, new = super(FadesUnseen, model).step_unplanted(mine, frame, weights)  # the method's own
        if before_feet:
            faded_frame, new = model._fade(mine, frame, out, new)
            want, feet = plant_frame(model.planter, faded_frame, mine)
        else:
            planted, feet = plant_frame(model.planter, out, mine)
            want, new = model._fade(mine, frame, planted, new)
            other, _ = plant_frame(model.planter, model._fade(mine, frame, out, dict(new))[0], mine)
            differs = differs or not np.array_equal(other.rotations, want.rotations)
        mine = {**new, **feet}
        np.testing.assert_array_equal(got.rotations, want.rotations)
        np.testing.assert_array_equal(got.root, want.root)
    assert before_feet or differs
