"""Style-ERD: causal features, streaming == whole-window forward, batching, causality, labels,
and the committed weights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.interface import FrameBatch, State, StreamingModel, stack_states  # noqa: E402 (after the torch check)
from models.motion.skeleton import fk  # noqa: E402
from tests.clips import frame_row, stylise_stream  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO / "models" / "weights" / "erd"

pytestmark = pytest.mark.skipif(not (WEIGHTS / "erd.npz").exists(), reason="Style-ERD weights not committed")


def split_state(state: State) -> list[State]:
    """One state per session: the inverse of `stack_states`."""
    n = len(next(iter(state.values())))
    return [{key: value[i : i + 1] for key, value in state.items()} for i in range(n)]


@pytest.fixture(scope="module")
def model():
    """The served model: network in float32."""
    import models.erd

    torch.set_num_threads(1)
    return models.erd.load(WEIGHTS)


@pytest.fixture(scope="module")
def reference():
    """The same weights with the network in float64: the reference the float32 model is held to."""
    from models.erd.runtime import load

    return load(WEIGHTS, dtype=np.float64)


@pytest.fixture(scope="module")
def walks():
    try:
        from models.data import build_index, load_motions, select

        clips = select(
            build_index(["bandai-namco-2"]), split="val", style="normal", content=("walk", "wave-right-hand")
        )
    except Exception as exc:  # dataset not unpacked on this machine
        pytest.skip(f"Bandai Namco dataset 2 unavailable: {exc}")
    clips = [c for c in clips if c.content == "walk"][:2] + [c for c in clips if c.content != "walk"][:1]
    return [m.slice(0, 48) for m in load_motions(clips)]


def _onehot(model, style, scale=1.0):
    w = np.zeros(len(model.styles()))
    w[model.styles().index(style)] = scale
    return w


def test_weights_small_and_protocol(model):
    size = sum(f.stat().st_size for f in WEIGHTS.iterdir())
    assert size < 10 * 2**20
    assert isinstance(model, StreamingModel)
    assert model.name == "erd"
    assert model.styles() == ["active", "elderly", "exhausted", "feminine", "masculine", "youthful"]
    assert model.skeleton.num_joints == 22 and model.skeleton.names[1] == "Hips"
    assert (WEIGHTS / "MODEL_CARD.md").exists()


def test_features_match_foundation(model, walks):
    from models.erd.features import CONTACT, NB, POS, ROOTVEL, VEL, YAWRATE
    from models.motion.features import compute_features

    motion = walks[0]
    x, yaw = model.maker.sequence(motion.translations[:, 1], motion.rotations)
    ref = compute_features(motion)
    F = motion.num_frames
    np.testing.assert_allclose(yaw, ref.yaw, atol=1e-6)
    np.testing.assert_allclose(x[:, POS].reshape(F, NB, 3), ref.local_positions[:, 1:], atol=1e-3)
    np.testing.assert_allclose(x[:, VEL].reshape(F, NB, 3), ref.joint_velocities[:, 1:], atol=1e-2)
    np.testing.assert_allclose(x[:, ROOTVEL], ref.root_velocity, atol=1e-2)
    np.testing.assert_allclose(x[:, YAWRATE], ref.yaw_rate, atol=1e-4)
    assert np.array_equal(x[:, CONTACT] > 0.5, ref.contacts)
    # quaternions: unit, sign-continuous over the clip
    q = x[:, : 4 * NB].reshape(F, NB, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-6)
    assert ((q[1:] * q[:-1]).sum(-1) > 0).all()


def test_stream_equals_whole_window(model, walks):
    from models.erd.dataset import CONTENTS

    from .reference.erd_offline import stylise

    motion = walks[0].slice(0, 40)
    w = _onehot(model, "elderly")
    streamed = stylise_stream(model, motion, w, content="walk", input_style="normal")
    gen = model.torch_generator()
    whole = stylise(gen, model, motion, w, style_in=0, content=CONTENTS.index("walk"))
    np.testing.assert_allclose(streamed.rotations, whole.rotations, atol=2e-4)
    np.testing.assert_allclose(streamed.translations, whole.translations, atol=2e-2)  # cm; float32 torch
    streamed = stylise_stream(model, motion, w)  # unlabelled
    whole = stylise(gen, model, motion, w)
    np.testing.assert_allclose(streamed.rotations, whole.rotations, atol=2e-4)


# float64 equal to round-off; float32 to its own precision (BLAS sums a batch of 1 and of 3 in
# different orders; the LSTM cell state reaches ~10, so 1e-6 absolute is ~float32's last bit there)
@pytest.mark.parametrize("which,atol,rtol", [("reference", 1e-6, 1e-7), ("model", 1e-5, 1e-5)])
def test_batched_equals_per_session_and_no_mutation(which, atol, rtol, request, walks):
    model = request.getfixturevalue(which)
    B = len(walks)
    weights = np.stack(
        [
            _onehot(model, "elderly"),
            _onehot(model, "exhausted", 1.5),
            0.5 * _onehot(model, "active") + 0.5 * _onehot(model, "feminine"),
        ]
    )
    singles = [model.init_state(1, content="walk", input_style="normal"), model.init_state(1), model.init_state(1)]
    batched = stack_states(singles)
    for t in range(12):
        frames = FrameBatch(np.stack([m.translations[t, 1] for m in walks]), np.stack([m.rotations[t] for m in walks]))
        before = {k: v.copy() for k, v in batched.items()}
        out_b, new_b = model.step_batch(batched, frames, weights)
        for k in before:
            assert np.array_equal(before[k], batched[k]), f"step_batch mutated state[{k!r}]"
        for i in range(B):
            out_i, singles[i] = model.step_batch(singles[i], frame_row(frames, i), weights[i : i + 1])
            np.testing.assert_allclose(out_b.rotations[i], out_i.rotations[0], atol=atol, rtol=rtol)
            np.testing.assert_allclose(out_b.root[i], out_i.root[0], atol=atol, rtol=rtol)
        for i, s in enumerate(split_state(new_b)):
            for k in s:
                # the foot planter's state is world positions in cm (~100): 100x the absolute round-off
                tol = 100 * atol if k.startswith("feet_") else atol
                np.testing.assert_allclose(s[k], singles[i][k], atol=tol, rtol=rtol)
        batched = new_b


def test_causal(model, walks):
    """Changing frames > t never changes outputs <= t (whole-window torch forward, features included)."""
    from dataclasses import replace

    from models.erd.offline import stylise

    motion = walks[0].slice(0, 30)
    gen = model.torch_generator()
    w = _onehot(model, "exhausted")
    base = stylise(gen, model.maker, motion, w)
    t = 17
    rot = motion.rotations.copy()
    rot[t + 1 :, 2:] = rot[t + 1 :, 2:][:, ::-1]  # scramble joints in the future
    trans = motion.translations.copy()
    trans[t + 1 :, 1] += 25.0
    changed = stylise(gen, model.maker, replace(motion, rotations=rot, translations=trans), w)
    assert np.array_equal(base.rotations[: t + 1], changed.rotations[: t + 1])
    assert np.array_equal(base.translations[: t + 1], changed.translations[: t + 1])
    assert not np.allclose(base.rotations[t + 1 :], changed.rotations[t + 1 :])


def test_missing_labels_and_real_walk_finite(model, walks):
    motion = walks[0]
    for kwargs in ({}, {"content": "walk"}, {"input_style": "normal"}, {"content": "walk", "input_style": "normal"}):
        out = stylise_stream(model, motion.slice(0, 20), _onehot(model, "elderly"), **kwargs)
        assert np.isfinite(out.rotations).all() and np.isfinite(out.translations).all()
        np.testing.assert_allclose(np.linalg.norm(out.rotations, axis=-1), 1.0, atol=1e-6)
    # zero weights = neutral branch only; output stays close to a neutral input
    out = stylise_stream(model, motion, np.zeros(6), content="walk", input_style="normal")
    pos_in, pos_out = motion.global_positions(), out.global_positions()
    local_in = pos_in - pos_in[:, 1:2]
    local_out = pos_out - pos_out[:, 1:2]
    assert np.abs(local_out - local_in).mean() < 10.0  # cm


def test_float32_network_matches_float64_reference(model, reference):
    """The served float32 network stays within 0.01 degree per joint (and 0.01 cm of root) of the
    float64 reference over a long stream with style changes and a mix (the LSTM state must not
    let float32 round-off grow)."""
    from models.data import build_index, load_motions, select

    clip = max(select(build_index(["bandai-namco-2"]), split="val", style="normal"), key=lambda c: c.frames)
    motion = load_motions([clip])[0]
    assert motion.num_frames >= 250
    states = {m: m.init_state(1) for m in (model, reference)}
    worst_deg, worst_cm = 0.0, 0.0
    for t in range(motion.num_frames):
        w = _onehot(model, model.styles()[(t // 60) % 6])
        if t % 120 >= 90:
            w = 0.7 * _onehot(model, "elderly") + 0.5 * _onehot(model, "youthful")
        frames = FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1])
        outs = {}
        for m in (model, reference):
            outs[m], states[m] = m.step_batch(states[m], frames, w[None])
        dots = np.abs(np.sum(outs[model].rotations * outs[reference].rotations, -1))
        worst_deg = max(worst_deg, np.degrees(2 * np.arccos(np.clip(dots, 0, 1))).max())
        worst_cm = max(worst_cm, np.abs(outs[model].root - outs[reference].root).max())
    assert worst_deg < 0.01 and worst_cm < 0.01, (worst_deg, worst_cm)
    assert states[model]["h"].dtype == np.float32 and states[reference]["h"].dtype == np.float64


def test_bad_shapes_are_clear_errors(model):
    """The compiled kernels have no bounds checks: shapes are checked before they run."""
    rest = np.zeros((1, 22, 4))
    rest[..., 3] = 1.0
    state, w = model.init_state(1), _onehot(model, "elderly")[None]
    with pytest.raises(ValueError, match="rotations"):
        model.step_batch(state, FrameBatch(np.zeros((1, 3)), rest[:, :21]), w)
    with pytest.raises(ValueError, match="prev_pos"):
        model.step_batch({**state, "prev_pos": np.zeros((1, 21, 3))}, FrameBatch(np.zeros((1, 3)), rest), w)
    with pytest.raises(ValueError, match="style_weights"):
        model.step_batch(state, FrameBatch(np.zeros((1, 3)), rest), w[:, :4])


def test_planted_feet_stay_put(model, walks):
    """The network alone slides its planted toes at walking speed (it knows nothing of the floor);
    the output holds them, and a leg it reports planted keeps its held toe or ankle in place."""
    from models.erd.offline import stylise

    from .reference.foot_slide import planted_slide

    motion = walks[0].slice(0, 150)
    w = _onehot(model, "active")
    gen = model.torch_generator()
    free = np.median(planted_slide(stylise(gen, model.maker, motion, w, foot_lock=False))["toe"])
    planted = np.median(planted_slide(stylise(gen, model.maker, motion, w))["toe"])
    assert free > 20.0 and planted < 1.0, (free, planted)  # cm/s
    state, points, held = model.init_state(1), [], []
    sk = model.skeleton
    feet = [sk.index(n) for n in ("Foot_L", "Toes_L", "Foot_R", "Toes_R")]
    for t in range(motion.num_frames):
        out, state = model.step_batch(
            state, FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1]), w[None]
        )
        translations = np.broadcast_to(sk.offsets, (1, sk.num_joints, 3)).copy()
        translations[:, 1] = out.root
        points.append(fk(out.rotations, translations, sk.parents)[1][0, feet].reshape(2, 2, 3))
        held.append(out.contacts[0])
    step = np.linalg.norm(np.diff(np.array(points)[..., [0, 2]], axis=0), axis=-1).min(
        -1
    )  # (F-1, 2 legs): the stiller point
    both = np.array(held[1:]) & np.array(held[:-1])
    # held exactly, but for the odd frame where the held leg cannot reach (cm per frame)
    assert both.sum() > 20 and np.median(step[both]) < 1e-6 and np.all(step[both] < 0.3), np.sort(step[both])[-8:]


def test_a_held_foot_moves_the_root_rather_than_jerking_the_thigh(model):
    """Past a few cm a held foot's hold is taken by the root (`GIVE_SPEED`): at LTI's 30 cm/s the
    legs took the rest, and elderly's thighs turning with the body through a walk-turn jerked at
    1.7-2.0x the input's p99 rotation acceleration; now about the input's own."""
    from dataclasses import replace

    from models.data import build_index, load_motions, select
    from models.eval.plausibility import rotation_acceleration

    from .clips import streamed_rotations

    thighs = np.array([model.skeleton.index(n) for n in ("UpperLeg_L", "UpperLeg_R")])
    clips = select(build_index(["bandai-namco-2"]), dataset="bandai-namco-2", split="val", style="normal")
    for motion in load_motions([c for c in clips if c.content == "walk-turn-right"][:4]):
        motion = motion.slice(0, 120)
        out = replace(motion, rotations=streamed_rotations(model, motion, _onehot(model, "elderly")))
        ratio = np.percentile(rotation_acceleration(out, thighs), 99, axis=0) / np.percentile(
            rotation_acceleration(motion, thighs), 99, axis=0
        )
        assert ratio.max() < 1.4, ratio


def _five_frames_in(model, motion):
    """(motion, elderly weights, the state of one session after motion's first 5 frames)."""
    w = _onehot(model, "elderly")[None]
    state = model.init_state(1)
    for t in range(5):
        _, state = model.step_batch(
            state, FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1]), w
        )
    return motion, w, state


def test_a_state_saved_before_the_foot_planter_still_steps(model, walks):
    """Snapshots written by an older replica have no planter state (or the old foot lock's):
    `upgrade_state` (which the service's batcher applies to every state) gives them a fresh one."""
    motion, w, state = _five_frames_in(model, walks[0])
    old = {**{k: v for k, v in state.items() if not k.startswith("feet_")}, "lock_anchor": np.zeros((1, 2, 3))}
    fresh = {**state, **{k: v for k, v in model.init_state(1).items() if k.startswith("feet_")}}
    assert model.upgrade_state(state) is state
    frame = FrameBatch(motion.translations[5:6, 1], motion.rotations[5:6])
    upgraded, _ = model.step_batch(model.upgrade_state(old), frame, w)
    expected, _ = model.step_batch(fresh, frame, w)
    np.testing.assert_array_equal(upgraded.rotations, expected.rotations)


def test_a_state_saved_before_the_averaged_gait_speed_still_steps(model, walks):
    """Snapshots from a replica before `gait_speed` (and before the foot planter): the average
    restarts from the next frame's speed, the rest of the state is kept."""
    motion, w, state = _five_frames_in(model, walks[0])
    frame = FrameBatch(motion.translations[5:6, 1], motion.rotations[5:6])
    for old in (
        {k: v for k, v in state.items() if k != "gait_speed"},
        {k: v for k, v in state.items() if k != "gait_speed" and not k.startswith("feet_")},
    ):
        up = model.upgrade_state(old)
        assert up["gait_speed"][0] < 0 and all(np.array_equal(up[k], v) for k, v in old.items())
        _, after = model.step_batch(up, frame, w)
        assert after["gait_speed"][0] > 0  # measured again from this frame


def test_a_state_saved_before_the_slow_copies_still_steps(model, walks):
    """Snapshots from a replica before the priors' slow copies (`slow_carry.py`): unset copies
    (zeros) that start again from the next frame, the rest of the state kept."""
    motion, w, state = _five_frames_in(model, walks[0])
    frame = FrameBatch(motion.translations[5:6, 1], motion.rotations[5:6])
    slow = ("leaf_prior/slow", "output_prior/slow")
    old = {k: v for k, v in state.items() if k not in slow}
    up = model.upgrade_state(old)
    assert not up[slow[0]].any() and not up[slow[1]].any()
    assert all(np.array_equal(up[k], v) for k, v in old.items())
    _, after = model.step_batch(up, frame, w)
    np.testing.assert_allclose(
        after[slow[0]][0],
        motion.rotations[5] / np.linalg.norm(motion.rotations[5], axis=-1, keepdims=True),
        atol=1e-12,
    )


def test_a_state_from_before_the_stage_pipeline_keeps_its_slow_copies(model, walks):
    """Snapshots from a replica that kept the slow copies as `slow_in` / `slow_out` step on as the
    state they are."""
    motion, w, state = _five_frames_in(model, walks[0])
    frame = FrameBatch(motion.translations[5:6, 1], motion.rotations[5:6])
    old = {k: v for k, v in state.items() if "/" not in k}
    old.update(slow_in=state["leaf_prior/slow"], slow_out=state["output_prior/slow"])
    want, _ = model.step_batch(state, frame, w)
    got, _ = model.step_batch(model.upgrade_state(old), frame, w)
    np.testing.assert_array_equal(got.rotations, want.rotations)
