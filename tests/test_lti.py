"""LTI style translation (Hsu et al. 2005): identification, streaming, batching, IMW, erf blend."""

from __future__ import annotations

import numpy as np
import pytest

from models.interface import FrameBatch
from models.lti import representation as rep
from models.lti.footplant import FootplantClassifier
from models.lti.model import WEIGHTS_DIR, LTIStyleModel, StyleTranslator
from models.lti.subspace import (
    StateSpace,
    fit_bd,
    noise_energy,
    spectral_radius,
    stabilize,
    subspace_id,
)
from models.lti.warping import imw, time_warp_dp
from models.motion.feet import LEG_JOINTS
from models.motion.rotations import yaw_quat

from .reference.lti_offline import features_to_sequence, static_to_rotations
from .reference.lti_offline import offline as reference_offline
from .reference.lti_subspace import simulate


def _data():
    """The real data (tests unpack it on first use)."""
    from models.data import build_index, load_motion, select

    return build_index(["bandai-namco-2"]), load_motion, select


def _one_hot(model: LTIStyleModel, style: str, batch: int) -> np.ndarray:
    w = np.zeros((batch, len(model.styles())))
    w[:, model.styles().index(style)] = 1.0
    return w


def _model(style="elderly") -> LTIStyleModel:
    """The committed weights must exist: a missing file fails the test."""
    assert (WEIGHTS_DIR / f"{style}.npz").exists(), "committed LTI weights missing"
    return LTIStyleModel()


# --------------------------------------------------------------------------- identification


def _markov(ss: StateSpace, k: int) -> np.ndarray:
    """Impulse response D, CB, CAB, ... up to k terms: (k, p, m); a system's input-output
    behaviour whatever its state basis."""
    out, x = [ss.D], ss.B
    for _ in range(k - 1):
        out.append(ss.C @ x)
        x = ss.A @ x
    return np.stack(out)


def test_identification_recovers_known_system():
    rng = np.random.default_rng(0)
    n, m, p = 4, 2, 3
    lam = rng.uniform(0.3, 0.9, n) * np.sign(rng.standard_normal(n))
    Q = rng.standard_normal((n, n))
    A = Q @ np.diag(lam) @ np.linalg.inv(Q)
    B, C, D = rng.standard_normal((n, m)), rng.standard_normal((p, n)), rng.standard_normal((p, m))
    records = []
    for _ in range(4):
        u = rng.standard_normal((300, m))
        records.append((u, simulate(A, B, C, D, u)))
    ss = subspace_id(records, horizon=8, ridge=1e-12)
    assert ss.order == n  # read off the singular-value gap
    np.testing.assert_allclose(np.sort(np.abs(np.linalg.eigvals(ss.A))), np.sort(np.abs(lam)), atol=1e-7)
    true = _markov(StateSpace(A, B, C, D), 40)
    assert np.abs(_markov(ss, 40) - true).max() < 1e-7 * np.abs(true).max()
    u = rng.standard_normal((200, m))  # fresh input: same simulated output
    np.testing.assert_allclose(simulate(ss.A, ss.B, ss.C, ss.D, u), simulate(A, B, C, D, u), atol=1e-6)


def _small_system(seed: int, n: int = 3, m: int = 2, p: int = 2):
    rng = np.random.default_rng(seed)
    A = np.diag(rng.uniform(-0.8, 0.8, n))
    return A, rng.standard_normal((n, m)), rng.standard_normal((p, n)), rng.standard_normal((p, m)), rng


def test_noise_energy_is_the_output_energy_of_white_input_noise():
    A, B, C, D, rng = _small_system(2)
    sigma, frames = np.array([0.5, 2.0]), 200_000
    theta = np.concatenate([B.T.ravel(), D.ravel()])  # fit_bd's unknowns: vec(B^T), vec(D)
    predicted = theta @ noise_energy(A, C, sigma, frames) @ theta
    simulated = np.sum(simulate(A, B, C, D, rng.standard_normal((frames, 2)) * sigma) ** 2)
    assert simulated == pytest.approx(predicted, rel=0.02)


def test_noise_aware_fit_is_least_squares_on_noisy_inputs():
    """fit_bd with input_noise = the fit on many noisy copies of the input (its expectation)."""
    A, B, C, D, rng = _small_system(3)
    u = rng.standard_normal((400, 2))
    y = simulate(A, B, C, D, u) + 0.1 * rng.standard_normal((400, 2))
    sigma = np.array([0.0, 0.7])  # the second input is noisy
    B_fit, D_fit = fit_bd(A, C, [(u, y)], ridge=1e-12, input_noise=sigma)
    copies = [(u + rng.standard_normal(u.shape) * sigma, y) for _ in range(400)]
    B_mc, D_mc = fit_bd(A, C, copies, ridge=1e-12)
    np.testing.assert_allclose(B_fit, B_mc, atol=0.05)
    np.testing.assert_allclose(D_fit, D_mc, atol=0.05)
    B_plain, _ = fit_bd(A, C, [(u, y)], ridge=1e-12)
    assert np.linalg.norm(B_fit[:, 1]) < np.linalg.norm(B_plain[:, 1])  # the noisy input is trusted less


def test_stabilize_reflects_unstable_eigenvalues():
    rng = np.random.default_rng(1)
    A = rng.standard_normal((6, 6))
    assert spectral_radius(A) > 1
    A2, changed = stabilize(A, 0.995)
    assert changed > 0 and spectral_radius(A2) <= 0.995 + 1e-9
    assert np.isrealobj(A2)


# --------------------------------------------------------------------------- representation


def test_representation_roundtrip():
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk-turn-left", split="val")[0])
    ref = rep.mean_rotations(m.rotations)
    f = rep.motion_to_features(m, ref)
    # relative to the reference no joint comes near the expmap's wrap-around at pi
    assert np.linalg.norm(f[:, 4:].reshape(len(f), 21, 3), axis=-1).max() < 2.5
    yaw0, _ = rep.split_hips(m.rotations[0, rep.HIPS])
    root, rots = features_to_sequence(f, m.translations[0, rep.HIPS, [0, 2]], float(yaw0), ref)
    np.testing.assert_allclose(root, m.translations[:, rep.HIPS], atol=1e-8)
    np.testing.assert_allclose(np.abs(np.sum(rots * m.rotations, -1)), 1.0, atol=1e-10)


# --------------------------------------------------------------------------- streaming


@pytest.mark.parametrize("footlock,keep_heading", [(False, False), (True, True)])
def test_streaming_equals_offline(footlock, keep_heading):
    _model()
    model = LTIStyleModel(footlock=footlock, keep_heading=keep_heading)
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk", split="val")[0])
    offline, contacts = reference_offline(model, "elderly", m, footlock=footlock)
    state, w = model.init_state(1), _one_hot(model, "elderly", 1)
    for t in range(m.num_frames):
        out, state = model.step_batch(state, FrameBatch(m.translations[t : t + 1, rep.HIPS], m.rotations[t : t + 1]), w)
        np.testing.assert_allclose(out.root[0], offline.translations[t, rep.HIPS], atol=1e-8)
        np.testing.assert_allclose(out.rotations[0], offline.rotations[t], atol=1e-10)
        assert (out.contacts[0] == contacts[t]).all()


def test_batched_step_equals_per_session():
    model = _model()
    index, load_motion, select = _data()
    clips = select(index, style="normal", content=("walk", "run", "wave-left-hand"), split="val")[:3]
    motions = [load_motion(c) for c in clips]
    frames = min(mo.num_frames for mo in motions)
    batch_state = model.init_state(len(motions))
    single = [model.init_state(1) for _ in motions]
    wb, w1 = _one_hot(model, "elderly", len(motions)), _one_hot(model, "elderly", 1)
    for t in range(frames):
        fb = FrameBatch(
            np.stack([mo.translations[t, rep.HIPS] for mo in motions]), np.stack([mo.rotations[t] for mo in motions])
        )
        out, batch_state = model.step_batch(batch_state, fb, wb)
        for k, mo in enumerate(motions):
            o, single[k] = model.step_batch(
                single[k], FrameBatch(mo.translations[t : t + 1, rep.HIPS], mo.rotations[t : t + 1]), w1
            )
            np.testing.assert_allclose(out.root[k], o.root[0], atol=1e-9)
            np.testing.assert_allclose(out.rotations[k], o.rotations[0], atol=1e-10)


def _offline_mix(model: LTIStyleModel, motion, w: np.ndarray):
    """Float64 numpy reference of a constant style mix (foot lock off), built from each style's
    offline translation: the input's share 1 - sum(w) plus each style's share of the root
    features (displacement, yaw change, height), body rotations blended by sign-aligned
    normalised quaternion averaging (each style's held inside its rotation prior first), the path
    integrated from the input's first frame."""
    from models.motion.hinge import kernel_floor
    from models.motion.hinge_kernels import floor_bends
    from models.motion.rotations import quat_mul
    from tests.reference.rotation_ball import clamp_rotations

    root, rots, F = motion.translations[:, rep.HIPS], motion.rotations, motion.num_frames
    yaw, tilt = rep.split_hips(rots[:, rep.HIPS])
    rest = max(1.0 - w.sum(), 0.0)
    root_feats = rest * np.concatenate([rep.sequence_features(root, rots)[:, :3], root[:, 1:2]], axis=1)
    body_in = rots.copy()
    body_in[:, rep.HIPS] = tilt
    parts, votes = [(rest, body_in)], np.zeros((F, 2))
    for s, style in enumerate(model.styles()):
        if w[s] > 0:
            tr = model.translators[style]
            out, xs = tr.translate_features(rep.motion_to_features(motion, tr.ref), model.blend, model.saturate)
            root_feats += w[s] * out[:, :4]
            body = static_to_rotations(out[:, 4 : rep.FEATURE_DIM], np.zeros(F), tr.ref)
            body = clamp_rotations(body, tr.prior_mean, tr.prior_radii)  # each style's prior
            if model.hinges is not None:  # then its hinge joints held at their floor
                body = floor_bends(body, *kernel_floor(motion.skeleton, model.hinges))
            parts.append((w[s], body))
            votes += w[s] * tr.footplant.predict(xs)
    base = max(parts, key=lambda p: p[0])[1]
    acc = sum(wp * np.where(np.sum(q * base, -1, keepdims=True) < 0, -q, q) for wp, q in parts)
    body = acc / np.linalg.norm(acc, axis=-1, keepdims=True)
    out_yaw, ground = np.empty(F), np.empty((F, 2))
    out_yaw[0], ground[0] = yaw[0], root[0, [0, 2]]
    for t in range(1, F):
        out_yaw[t] = out_yaw[t - 1] + root_feats[t, 2]
        ground[t] = ground[t - 1] + rep.rotate_y(root_feats[t, :2], out_yaw[t - 1])
    body[:, 0] = (0.0, 0.0, 0.0, 1.0)
    body[:, rep.HIPS] = quat_mul(yaw_quat(out_yaw), body[:, rep.HIPS])
    return np.stack([ground[:, 0], root_feats[:, 3], ground[:, 1]], axis=1), body, votes > 0.5 * w.sum()


@pytest.mark.parametrize("mix", [{"elderly": 0.5, "exhausted": 0.3}, {"active": 0.9, "youthful": 0.6}])
def test_style_mix_equals_blend_of_offline_translations(mix):
    """The compiled step against the numpy reference for mixes with intensity < 1 and > 1 (the
    stages on the blend, the feet's, off: their references are `reference_offline`'s)."""
    _model()
    model = LTIStyleModel(footlock=False, off=("foot_pitch",))
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk", split="val")[0])
    w = np.array([mix.get(s, 0.0) for s in model.styles()])
    want_root, want_rot, want_contacts = _offline_mix(model, m, w)
    state = model.init_state(1)
    for t in range(m.num_frames):
        out, state = model.step_batch(
            state, FrameBatch(m.translations[t : t + 1, rep.HIPS], m.rotations[t : t + 1]), w[None]
        )
        np.testing.assert_allclose(out.root[0], want_root[t], atol=1e-8)
        np.testing.assert_allclose(out.rotations[0], want_rot[t], atol=1e-10)
        assert (out.contacts[0] == want_contacts[t]).all()


def test_zero_style_weights_pass_the_input_through():
    model = _model()
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk-turn-left", split="val")[0])
    state, w = model.init_state(1), np.zeros((1, len(model.styles())))
    for t in range(m.num_frames):
        out, state = model.step_batch(state, FrameBatch(m.translations[t : t + 1, rep.HIPS], m.rotations[t : t + 1]), w)
        np.testing.assert_allclose(out.root[0], m.translations[t, rep.HIPS], atol=1e-8)
        np.testing.assert_allclose(np.abs(np.sum(out.rotations[0] * m.rotations[t], -1)), 1.0, atol=1e-12)
        assert not out.contacts.any()


def test_a_held_pose_comes_out_held_from_its_first_frame():
    """Each system starts at the state its first input would settle it in, as a session starts
    and as a style is weighted in: a pose held still comes out still, not swung in from the
    mean pose over the first frames. (The legs are left out: a root system reads a standing
    pose as a slow pace, and the planter's leg IK follows the root it moves,
    `test_lti_standing.py`.)"""
    model = _model()
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk", split="val")[0])
    held = FrameBatch(m.translations[20:21, rep.HIPS], m.rotations[20:21])
    body = [j for j, name in enumerate(m.skeleton.names) if name not in LEG_JOINTS]
    for style in model.styles():
        state, rotations = model.init_state(1), []
        for t in range(12):  # the style weighted in on the 4th frame
            out, state = model.step_batch(state, held, _one_hot(model, style, 1) * (t >= 3))
            rotations.append(out.rotations[0, body])
        styled = np.array(rotations[3:])
        assert np.abs(np.abs(np.sum(styled * styled[0], -1)) - 1.0).max() < 1e-9, style
        assert np.abs(np.abs(np.sum(styled[0] * rotations[0], -1)) - 1.0).max() > 1e-6, style  # it is styled


def test_step_leaves_its_input_state_unchanged():
    model = _model()
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk", split="val")[0])
    state, w = model.init_state(2), _one_hot(model, "elderly", 2)
    w[1] = 0.0
    for t in range(40):
        fb = FrameBatch(np.repeat(m.translations[t : t + 1, rep.HIPS], 2, 0), np.repeat(m.rotations[t : t + 1], 2, 0))
        before = {k: v.copy() for k, v in state.items()}
        _, new = model.step_batch(state, fb, w)
        for k, v in before.items():
            assert np.array_equal(v, state[k]), f"step_batch changed state[{k!r}]"
        assert new.keys() == state.keys()
        state = new
    assert not state["x.elderly"][1].any()  # an inactive style rests at x = 0


def test_read_only_inputs_and_a_style_weighted_in_step_on_the_compiled_kernel():
    """numba compiles a kernel again for read-only arrays (~50 s in which no session gets a
    frame): a broadcast weight row, or a style weighted in from its read-only rest state, must
    step on the kernel already compiled."""
    from models.lti import kernels

    model = _model()
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk", split="val")[0])
    frame = FrameBatch(m.translations[:1, rep.HIPS], m.rotations[:1])
    first, second = model.styles()[:2]
    state = model.step_batch(model.init_state(1), frame, _one_hot(model, first, 1))[1]
    compiled = len(kernels.step.signatures)
    read_only = np.broadcast_to(_one_hot(model, second, 1)[0], (1, len(model.styles())))
    assert not read_only.flags.writeable and not state[f"x.{second}"].flags.writeable
    out, state = model.step_batch(state, frame, read_only)  # the second style weighted in from rest
    assert len(kernels.step.signatures) == compiled
    assert np.isfinite(out.rotations).all() and state[f"x.{second}"].any()


def test_float32_frames_and_list_weights_step_as_float64_without_compiling():
    """The step passes arrays to its kernel as they come and retries on copies when the kernel has
    no signature for them: float32 frames and a plain list of weights give the float64 result,
    and the kernel compiles nothing new."""
    from models.lti import kernels

    model = _model()
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk", split="val")[0])
    w = _one_hot(model, "elderly", 1)
    frames = [FrameBatch(m.translations[t : t + 1, rep.HIPS], m.rotations[t : t + 1]) for t in range(5)]
    want, as32, listed = model.init_state(1), model.init_state(1), model.init_state(1)
    model.step_batch(want, frames[0], w)  # compiled (or loaded) for the kernel's own types
    compiled = len(kernels.step.signatures)
    for f in frames:
        a, want = model.step_batch(want, f, w)
        b, as32 = model.step_batch(as32, FrameBatch(f.root.astype(np.float32), f.rotations.astype(np.float32)), w)
        c, listed = model.step_batch(listed, f, w.tolist())
        np.testing.assert_allclose(b.rotations, a.rotations, atol=1e-5)
        np.testing.assert_allclose(b.root, a.root, atol=1e-3)
        np.testing.assert_array_equal(c.rotations, a.rotations)
    assert len(kernels.step.signatures) == compiled


def test_bad_shapes_and_stale_states_are_clear_errors():
    """The compiled step has no bounds checks: shapes are checked before it runs."""
    model = _model()
    rest = np.zeros((1, 22, 4))
    rest[..., 3] = 1.0
    state, w = model.init_state(1), _one_hot(model, "elderly", 1)
    with pytest.raises(ValueError, match="rotations"):
        model.step_batch(state, FrameBatch(np.zeros((1, 3)), rest[:, :21]), w)
    with pytest.raises(ValueError, match="style_weights"):
        model.step_batch(state, FrameBatch(np.zeros((1, 3)), rest), w[:, :3])
    with pytest.raises(ValueError, match="carry"):
        model.step_batch({**state, "carry": np.zeros((2, 3))}, FrameBatch(np.zeros((1, 3)), rest), w)
    import copy

    smaller = copy.copy(model)
    smaller.remove_style("youthful")
    bigger_state = {**state, "x.youthful": np.zeros((1, 3))}  # a wrong size for a style this model has
    with pytest.raises(ValueError, match="upgrade_state"):
        model.step_batch(bigger_state, FrameBatch(np.zeros((1, 3)), rest), w)
    out, _ = smaller.step_batch(smaller.upgrade_state(state), FrameBatch(np.zeros((1, 3)), rest), w[:, :5])
    assert np.isfinite(out.rotations).all()


def test_trained_models_are_stable_and_listed():
    model = _model()
    assert "elderly" in model.styles()
    for tr in model.translators.values():
        assert spectral_radius(tr.A) < 1.0


# --------------------------------------------------------------------------- IMW


def test_imw_never_increases_objective():
    index, load_motion, select = _data()
    from models.lti.train import make_pairs, match_features

    a, b = make_pairs(index, "exhausted", "val")[0]
    fa, fb = rep.motion_to_features(load_motion(a)), rep.motion_to_features(load_motion(b))
    mean, std = fa.mean(0), np.maximum(fa.std(0), 0.05)
    res = imw(match_features(fa, mean, std), match_features(fb, mean, std), s=3, max_step=6, max_iter=6)
    obj = np.array(res.objective)
    assert len(obj) >= 3
    assert np.all(np.diff(obj) <= 1e-9 * obj[0])
    steps = np.diff(res.warp)
    assert res.warp[0] == 0 and res.warp[-1] == b.frames - 1
    assert steps.min() >= 1 / 3 - 1e-12 and steps.max() <= 2 + 1e-12


def test_time_warp_dp_finds_known_shift():
    rng = np.random.default_rng(2)
    K, T = 61, 31  # the best path advances 2 per row
    cost = rng.uniform(1, 2, (T, K))
    cost[np.arange(T), 2 * np.arange(T)] = 0
    path, total = time_warp_dp(cost, 3)
    np.testing.assert_array_equal(path, 2 * np.arange(T))
    assert total == 0


# --------------------------------------------------------------------------- erf blend and footplant


def _toy_translator() -> StyleTranslator:
    n, d = 2, rep.FEATURE_DIM
    z = np.zeros
    return StyleTranslator(
        "toy",
        0.5 * np.eye(n),
        z((n, d)),
        z((d + 1, n)),
        z((d + 1, d)),
        z(d),
        np.ones(d),
        z(d + 1),
        np.ones(d + 1),
        -np.ones(d),
        np.ones(d),
        np.array([n]),
        k_p=1.0,
        k_c=2.0,
    )


def test_erf_blend_zero_inside_and_one_far_outside():
    tr = _toy_translator()
    u = np.zeros((5, rep.FEATURE_DIM))
    u[1, 3] = 0.99  # inside [-1, 1]
    u[2, 3] = 1.9  # outside, but within k_p
    u[3, 10] = -4.0  # moderately outside
    u[4, 5] = 60.0  # far outside
    w = tr.blend_weight(u)
    assert w[0] == 0 and w[1] == 0 and w[2] == 0
    assert 0 < w[3] < 1
    assert w[4] > 0.999999
    # blended output: far outside the training range the input passes through
    feats = np.full((1, rep.FEATURE_DIM), 60.0)
    out, _ = tr.translate_features(feats)
    np.testing.assert_allclose(out[0, : rep.FEATURE_DIM], feats[0], rtol=1e-6)


def test_the_blend_eases_toward_the_input_when_it_leaves_the_training_range():
    """An input that leaves the training range in one frame (raw weight 0 -> 1) is blended toward
    over a few frames, with a small second difference (no rotation jolt), and reaches it."""
    from models.lti.model import ease_keep

    tr = _toy_translator()
    feats = np.zeros((60, rep.FEATURE_DIM))
    feats[10:, 5] = 60.0  # far outside from frame 10 on
    u = (feats - tr.in_mean) / tr.in_std
    raw = tr.blend_weight(u)
    assert raw[:10].max() == 0.0 and raw[10:].min() > 0.999999
    out, _ = tr.translate_features(feats)
    w = out[:, 5] / 60.0  # toy: the translation is 0, so the output is w * the input
    assert w[:10].max() == 0.0 and 0.0 < w[10] < 0.1
    assert np.abs(np.diff(w, 2)).max() < 2 * (1.0 - ease_keep(LTIStyleModel.fps)) ** 2
    assert w[10 + int(LTIStyleModel.fps)] > 0.99


def test_footplant_classifier_separates_classes():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((400, 5))
    labels = np.stack([x[:, 0] + 0.1 * rng.standard_normal(400) > 0, x[:, 1] > 0.5], axis=1)
    fp = FootplantClassifier.fit(x, labels)
    assert (fp.predict(x) == labels).mean() > 0.9


def test_offline_timewarp_follows_predicted_rate():
    model = _model()
    index, load_motion, select = _data()
    m = load_motion(select(index, style="normal", content="walk", split="val")[0])
    tr = model.translators["elderly"]
    out, _ = tr.translate_features(rep.motion_to_features(m, tr.ref))
    expected = 1 + np.exp(out[1:, rep.FEATURE_DIM]).sum()
    warped, contacts = model.translate(m, "elderly", timewarp=True)
    assert abs(warped.num_frames - expected) <= 1.0
    assert len(contacts) == warped.num_frames
    np.testing.assert_allclose(np.linalg.norm(warped.rotations, axis=-1), 1.0, atol=1e-9)


# --------------------------------------------------------------------------- the feet


def test_feet_land_heel_first_with_the_input_instead_of_skidding_flat(bn_walk):
    """The systems land a foot flat while the leg still swings forward; with its pitch halfway to
    the input's (`foot_pitch`) the heel strikes first and the sole comes down as the foot stops."""
    from models.eval.metrics import flat_foot_contacts, planted

    from .clips import stylise_stream

    w = _one_hot(_model(), "active", 1)[0]  # the style whose feet skidded most (docs/eval/ablation.md)
    slides = {}
    for off in ((), ("foot_pitch",)):
        out = stylise_stream(LTIStyleModel(off=off), bn_walk, w)
        slides[off] = np.percentile(planted(*flat_foot_contacts(out)), 95)  # cm/s over flat-foot frames
    assert slides[()] < 10.0  # real walks: 3-11 cm/s (`models.eval`'s slide references)
    assert slides[("foot_pitch",)] > 50.0
