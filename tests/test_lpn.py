"""LPN-FiLM runtime on the committed weights and real Bandai Namco clips: the numpy step is the
trained torch network, it is causal, control steers it, styles blend and can be added from a clip."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.data import build_index, load_motion, select
from models.interface import FrameBatch, StreamingModel
from models.lpn.dataset import clip_samples
from models.registry import load_models
from models.settings import get_settings
from tests.clips import concat_frames
from tests.lpn_films import blend_films, film_of, style_table

TARGETS = ("normal", "active", "elderly", "exhausted", "feminine", "masculine", "youthful")


@pytest.fixture(scope="module")
def model(lpn_model):
    return lpn_model


@pytest.fixture(scope="module")
def clips():
    index = build_index(["bandai-namco-1", "bandai-namco-2"])
    walk = load_motion(select(index, dataset="bandai-namco-2", split="val", style="normal", content="walk")[0])
    run = load_motion(select(index, dataset="bandai-namco-2", split="val", style="active", content="run")[0])
    giant = load_motion(select(index, dataset="bandai-namco-1", style="giant", content="walk")[0])
    return {"walk": walk, "run": run, "giant": giant}


def _frames(motion, t: int, control=None) -> FrameBatch:
    return FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1], control=control)


def _drive(model, control: np.ndarray, start, style: str = "normal") -> np.ndarray:
    """Hips path (T, 3) of one session driven by per-frame control rows from `start`'s first pose."""
    motion, _ = model.run(start, model.weight_vector({style: 1.0}), control=control)
    return motion.translations[:, 1]


def test_loads_through_the_registry_with_the_target_styles(model):
    models = load_models(get_settings().weights_dir)
    assert isinstance(models["lpn"], StreamingModel)
    assert models["lpn"].fps == 30.0 and models["lpn"].name == "lpn"
    assert set(TARGETS) <= set(models["lpn"].styles())
    assert not set(model.config["held_out"]) & set(model.styles())


def test_numpy_network_equals_the_trained_torch_network(model, clips):
    from tests.reference.lpn_step import in_float32

    samples = clip_samples(clips["walk"], gait=0.0)
    x, g = samples.X[::7][:16], samples.G[::7][:16]
    film = blend_films(model, np.tile(model.weight_vector({"elderly": 0.7, "active": 0.3}), (len(x), 1)))
    ours = in_float32(model)._network(x, g, film)
    net = model.generator()
    with torch.no_grad():
        theirs = net.denormalise_y(
            net(net.normalise_x(torch.from_numpy(x)), net.normalise_g(torch.from_numpy(g)), torch.from_numpy(film))
        ).numpy()
    scale = np.abs(theirs).mean(0) + 1e-3
    assert np.abs((ours - theirs) / scale).max() < 1e-3
    # in bfloat16 products (where this machine uses them) one prediction moves by rounding only
    fast = np.abs((model._network(x, g, film) - theirs) / scale)
    assert np.median(fast) < 1e-2 and fast.max() < 0.1


def test_step_never_reads_future_frames(model, clips):
    """Two sessions see the same frames up to t = 20, then different clips: outputs agree up to 20."""
    a, b = clips["walk"], clips["run"]
    state = model.init_state(2)
    w = np.tile(model.weight_vector({"elderly": 1.0}), (2, 1))
    outs = []
    for t in range(30):
        second = a if t <= 20 else b
        frames = concat_frames([_frames(a, t), _frames(second, t)])
        out, state = model.step_batch(state, frames, w)
        outs.append(out)
    for t in range(21):
        np.testing.assert_allclose(outs[t].root[0], outs[t].root[1], atol=1e-4)
        np.testing.assert_allclose(outs[t].rotations[0], outs[t].rotations[1], atol=1e-5)
    assert not np.allclose(outs[29].rotations[0], outs[29].rotations[1], atol=1e-3)


def test_sessions_in_a_batch_are_independent(model, clips):
    walk, run = clips["walk"], clips["run"]
    w = np.stack([model.weight_vector({"elderly": 1.0}), model.weight_vector({"active": 1.0})])
    both, alone = model.init_state(2), [model.init_state(1), model.init_state(1)]
    for t in range(12):
        out, both = model.step_batch(both, concat_frames([_frames(walk, t), _frames(run, t)]), w)
        for i, m in enumerate((walk, run)):
            single, alone[i] = model.step_batch(alone[i], _frames(m, t), w[i : i + 1])
            np.testing.assert_allclose(out.root[i], single.root[0], atol=1e-3)


def test_control_moves_the_character_where_it_is_asked(model, clips):
    T = 90
    walk_x = np.tile([[1.2, 0.0, np.pi / 2, 0.0, 1.0]], (T, 1))  # walk facing +X
    stand = np.tile([[0.0, 0.0, np.pi / 2, 0.0, 1.0]], (T, 1))
    moved = _drive(model, walk_x, clips["walk"])
    still = _drive(model, stand, clips["walk"])
    step = moved[-1] - moved[30]
    assert step[0] > 40.0 and abs(step[0]) > 2 * abs(step[2]), step  # cm in 2 s, mostly along +X
    assert np.linalg.norm((still[-1] - still[30])[[0, 2]]) < 0.5 * np.linalg.norm(step[[0, 2]])


def test_without_control_it_follows_the_input_path(model, clips):
    walk = clips["walk"]
    out, _ = model.run(walk, model.weight_vector({"normal": 1.0}), frames=90)
    src = walk.translations[:90, 1][:, [0, 2]]
    got = out.translations[:, 1][:, [0, 2]]
    d_src, d_got = src[-1] - src[0], got[-1] - got[0]
    cos = d_src @ d_got / (np.linalg.norm(d_src) * np.linalg.norm(d_got))
    assert cos > 0.8 and 0.4 < np.linalg.norm(d_got) / np.linalg.norm(d_src) < 2.0


def test_style_weights_blend_film_vectors_and_lean_to_normal(model):
    e, a, n = (film_of(model, s) for s in ("elderly", "active", "normal"))
    mix = blend_films(model, model.weight_vector({"elderly": 0.5, "active": 0.5})[None])[0]
    np.testing.assert_allclose(mix, 0.5 * (e + a), atol=1e-5)
    half = blend_films(model, model.weight_vector({"elderly": 0.5})[None])[0]
    np.testing.assert_allclose(half, 0.5 * (e + n), atol=1e-5)
    with pytest.raises(ValueError):
        blend_films(model, np.ones((1, 3)))


def test_styles_change_the_motion(model, clips):
    control = np.tile([[1.2, 0.0, 0.0, 0.0, 1.0]], (60, 1))
    paths = {
        s: model.run(clips["walk"], model.weight_vector({s: 1.0}), control=control)[0] for s in ("normal", "elderly")
    }
    pose = {s: m.rotations[30:] for s, m in paths.items()}
    assert np.abs(pose["normal"] - pose["elderly"]).mean() > 0.01


def test_add_style_from_clip_gives_a_usable_style_and_remove_drops_it(lpn_model, clips):
    model = lpn_model.with_own_styles()
    model.add_style_from_clip("giant-from-clip", clips["giant"])
    try:
        assert model.styles()[-1] == "giant-from-clip"
        film = film_of(model, "giant-from-clip")
        assert np.isfinite(film).all() and not np.allclose(film, film_of(model, "normal"), atol=1e-3)
        state = model.init_state(1)
        w = model.weight_vector({"giant-from-clip": 1.0})[None]
        out, state = model.step_batch(state, _frames(clips["walk"], 0), w)
        assert np.isfinite(out.rotations).all()
    finally:
        model.remove_style("giant-from-clip")
    assert "giant-from-clip" not in model.styles()
    with pytest.raises(ValueError):
        model.add_style_from_clip("tiny", clips["giant"].slice(0, 10))
    with pytest.raises(ValueError):
        model.remove_style("normal")


def test_an_upload_gets_an_output_prior_fitted_from_its_clip(lpn_model, clips, tmp_path):
    """The clip's style carries an output prior of its own: the upper body carried toward the
    clip's rotations, every other joint left as it is, and the prior's rows on for the upload
    alone; the same vector installed without it gets rows that change nothing. The prior moves
    the stream's upper body toward the clip's mean pose."""
    from models.lpn.output_prior import CARRIED
    from models.lpn.styles import LPNUpload
    from models.motion.rotations import quat_mean

    model = lpn_model.with_own_styles()
    giant = clips["giant"]
    upload = model.style_from_clip(giant)
    assert upload.prior is not None and upload.prior.map.shape[0] == 1
    names = model.skeleton.names
    carried = [j for j, n in enumerate(names) if n in CARRIED]
    fixed = [j for j, n in enumerate(names) if n not in CARRIED]
    assert np.all(upload.prior.radius[0, fixed] == np.pi) and np.all(upload.prior.radius[0, carried] < np.pi)
    model.install_style("up", upload)
    bare = model.with_own_styles()
    bare.install_style("up", LPNUpload(upload.film))
    rows = style_table(model).rows["output_prior"]["on"]
    assert rows[model.styles().index("up")] == 1.0 and style_table(bare).rows["output_prior"]["on"][-1] == 0.0

    def gap(m) -> float:
        out = m.run(clips["walk"], m.weight_vector({"up": 1.0}))[0].rotations[30:, carried]
        want = quat_mean(giant.rotations[:, carried], axis=0)
        return float(np.mean(1.0 - np.abs(np.sum(quat_mean(out, axis=0) * want, axis=-1))))

    assert gap(model) < gap(bare)
    model.save_style(upload, tmp_path)  # a fine-tuned style is saved with its prior, and loads back whole
    loaded = model.load_style("up", tmp_path)
    assert loaded.prior is not None
    for a, b in zip(loaded.prior.arrays, upload.prior.arrays):
        np.testing.assert_array_equal(a, b)


def test_control_sessions_start_standing_whatever_pose_the_input_carries(model):
    """A controller client sends no pose (the service passes the identity rest pose): the session
    starts from the model's standing pose facing the control's yaw, and walks that way."""
    identity = np.zeros((1, 22, 4))
    identity[..., 3] = 1.0
    w = model.weight_vector({"normal": 1.0})[None]
    roots = {}
    for facing in (0.0, np.pi / 2):
        state = model.init_state(1)
        for t in range(60):
            control = np.array([[1.2, 0.0, facing, 0.0, 1.0]])
            out, state = model.step_batch(state, FrameBatch(np.zeros((1, 3)), identity, control=control), w)
            if t == 0:
                assert 70.0 < out.root[0, 1] < 110.0  # Hips at standing height, not the rest pose's
        roots[facing] = out.root[0]
    assert roots[0.0][2] > 40.0 and abs(roots[0.0][0]) < 0.5 * roots[0.0][2]
    assert roots[np.pi / 2][0] > 40.0 and abs(roots[np.pi / 2][2]) < 0.5 * roots[np.pi / 2][0]


@pytest.fixture(scope="module")
def reference(model):
    """The numpy step the compiled kernels replaced, on the same weights."""
    from tests.reference.lpn_step import numpy_twin

    return numpy_twin(model)


def test_compiled_step_gives_the_numpy_steps_outputs(model, reference, clips):
    """Four sessions in one batch for 100 frames, each in its own style: two driven by control (walk
    ahead, turn to +X, stop; a side-stepping run), two by input frames (a walk; a run, then its last
    frame held). The compiled step gives the numpy step's outputs and state every frame, to float32
    round-off (velocities, differences of positions x 30 fps, carry the most), through every case of
    the foot planter: feet held planted, released, and legs bent by its IK to hold them."""
    T, walk, run = 100, clips["walk"], clips["run"]
    ahead = np.tile([1.2, 0.0, 0.0, 0.0, 1.0], (T, 1))
    ahead[40:70, [0, 2]] = [1.5, np.pi / 2]
    ahead[70:, [0, 2]] = [0.0, np.pi / 2]
    side = np.tile([0.4, 0.9, -0.5, 1.0, 1.0], (T, 1))
    weights = np.stack(
        [
            model.weight_vector(mix)
            for mix in ({"elderly": 1.0}, {"active": 1.0}, {"feminine": 0.5, "exhausted": 0.3}, {"normal": 1.0})
        ]
    )
    from tests.reference.lpn_step import in_float32

    model = in_float32(model)  # the reference multiplies in float32
    # the arm coupling moves a forearm by up to ~10x its drivers' deviations, round-off included: it
    # has its own compiled-vs-numpy test (test_lpn_arm_coupling.py); here the step before it
    model, reference = model.with_own_styles(), reference.with_own_styles()
    model.stages = model.stages.without("arm_coupling")
    reference.stages = reference.stages.without("arm_coupling")
    states = {m: m.init_state(4) for m in (model, reference)}
    worst = {"root_cm": 0.0, "quaternion": 0.0, "state": 0.0}
    roots, held, released, bent = [], [], [], []
    for t in range(T):
        frames = concat_frames(
            [
                _frames(walk, 0, ahead[t : t + 1]),
                _frames(walk, 0, side[t : t + 1]),
                _frames(walk, t),
                _frames(run, min(t, run.num_frames - 1)),
            ]
        )  # then stands on its last frame
        outs, before = {}, states[model]
        for m in (model, reference):
            outs[m], states[m] = m.step_batch(states[m], frames, weights)
        ours, theirs = outs[model], outs[reference]
        np.testing.assert_array_equal(ours.contacts, theirs.contacts)
        roots.append(ours.root)
        after = states[model]
        held.append(before["feet_contact"] & after["feet_contact"])  # (4 sessions, 2 feet) planted now and before
        released.append(before["feet_contact"] & ~after["feet_contact"])
        bent.append(held[-1] & (np.linalg.norm(after["feet_offset"], axis=-1) > 0.1))  # the IK holds it > 1 mm
        worst["root_cm"] = max(worst["root_cm"], np.abs(ours.root - theirs.root).max())
        sign = np.sign(np.sum(ours.rotations * theirs.rotations, -1, keepdims=True))  # q and -q: the same rotation
        worst["quaternion"] = max(worst["quaternion"], np.abs(ours.rotations - sign * theirs.rotations).max())
        for key, value in states[model].items():
            expected = states[reference][key]
            assert value.dtype == expected.dtype and value.shape == expected.shape, key
            error = np.abs(value.astype(np.float64) - expected).max() / (1.0 + np.abs(expected).max())  # of its scale
            worst["state"] = max(worst["state"], error)
    travelled = np.linalg.norm(roots[-1][:, [0, 2]] - roots[0][:, [0, 2]], axis=-1)
    assert (travelled > 50.0).all(), travelled  # every session walked or ran: the comparison covers real motion
    # and every session plants and releases both feet; the IK holds planted feet in most sessions
    assert np.any(held, axis=0).all() and np.any(released, axis=0).all()
    assert np.sum(bent) >= 20 and np.any(bent, axis=(0, 2)).sum() >= 2, np.sum(bent, axis=0)
    # the network's float32 products alone are ~5e-5 (relative) off float64; the rest is float64 here
    assert worst["root_cm"] < 1e-3 and worst["quaternion"] < 5e-4 and worst["state"] < 1e-4, worst


def test_step_refuses_a_state_that_does_not_fit_the_frames(model, clips):
    """The compiled kernels have no bounds checks: a state of the wrong shape or dtype is a clear
    error before they run, never a read past an array."""
    w = model.weight_vector({"normal": 1.0})[None]
    _, state = model.step_batch(model.init_state(1), _frames(clips["walk"], 0), w)
    for key, bad in (("hist_phase", state["hist_phase"][:, :10]), ("pose", state["pose"].astype(np.float64))):
        with pytest.raises(ValueError, match=key):
            model.step_batch({**state, key: bad}, _frames(clips["walk"], 1), w)
    with pytest.raises(ValueError, match="rotations"):
        model.step_batch(state, FrameBatch(np.zeros((1, 3)), np.ones((1, 21, 4))), w)


def test_a_long_clips_style_features_in_blocks_equal_them_in_one_go(bn_walk):
    """Worked out in blocks (so no numpy call spans the clip, beside the service's event loop),
    a clip longer than a block has exactly the features it has in one go, block seams included."""
    from dataclasses import replace

    from models.lpn.dataset import STYLE_FEATURE_BLOCK, _style_features_in_one_go, clip_style_features

    frames = 2 * STYLE_FEATURE_BLOCK + 37
    reps = -(-frames // bn_walk.num_frames)
    long = replace(
        bn_walk,
        rotations=np.tile(bn_walk.rotations, (reps, 1, 1))[:frames],
        translations=np.tile(bn_walk.translations, (reps, 1, 1))[:frames],
    )
    np.testing.assert_array_equal(clip_style_features(long), _style_features_in_one_go(long))


def test_a_normalised_film_generator_keeps_telling_clips_apart_when_its_units_drift_negative():
    """The failure `LPNConfig.film_norm` prevents (the LPN-FiLM model card): once the second
    convolution's outputs all sit below zero, ELU passes -1 for every clip and every style gets the
    same FiLM vector."""
    import torch

    from models.lpn.network import LPN, LPNConfig

    torch.manual_seed(0)
    windows = torch.randn(2, 120, LPNConfig.style_dim)
    films = {}
    for norm in (False, True):
        gen = LPN(LPNConfig(hidden=32, filters=16, film_norm=norm)).film
        torch.nn.init.normal_(gen.out.weight)
        with torch.no_grad():
            gen.conv2.bias.fill_(-1e3)  # every unit far below zero, as in the collapsed runs
            films[norm] = gen(windows)
    assert torch.allclose(films[False][0], films[False][1])
    assert (films[True][0] - films[True][1]).abs().max() > 0.1


def test_the_torso_turns_as_smoothly_as_real_walks(model, bn_walk):
    """The network can turn the spine ~180 degrees about itself and the chest back over a few
    frames; in between the pair bent against each other (the chest joint dropped 8 cm for one
    frame). Real validation walks never change the spine's or chest's rotation by more than ~6
    degrees per frame per frame; every style's output stays under 10 (model card)."""
    from models.motion.rotations import quat_inv, quat_log, quat_mul

    walk = bn_walk.slice(0, 90)
    torso = [model.skeleton.index("Spine"), model.skeleton.index("Chest")]
    for style in model.styles()[:7]:  # the dataset-2 styles, normal first
        q = model.run(walk, model.weight_vector({style: 1.0}))[0].rotations[:, torso].astype(np.float64)
        step = quat_log(quat_mul(quat_inv(q[:-1]), q[1:]))
        assert np.degrees(np.linalg.norm(np.diff(step, axis=0), axis=-1)).max() < 10.0, style


def test_a_copy_whose_stages_change_checks_the_state_its_own_stages_make(model, clips):
    """A copy (`with_own_styles`, as an upload's fit makes one) that switches a stage off steps
    with the state its own stages make: the step's state check must not keep the layout the
    model it was copied from had cached, or a stage with state could never be switched off."""
    from dataclasses import dataclass

    from models.lpn.output_prior import OutputPrior

    @dataclass(frozen=True)
    class Counting(OutputPrior):
        """The output prior with a state of its own, as a stage that follows the motion has."""

        def init_state(self, batch: int) -> dict[str, np.ndarray]:
            return {"frames": np.zeros((batch, 1))}

        def step_batch(self, state, frame, rows):
            out, _ = super().step_batch(state, frame, rows)
            return out, {"frames": state["frames"] + 1.0}

    stateful = model.with_own_styles()
    prior = stateful.stages.output_prior
    stateful.stages = stateful.stages.replace(output_prior=Counting(prior.styles, prior.carry, prior.run))
    w = stateful.weight_vector({"elderly": 1.0})[None]
    _, state = stateful.step_batch(stateful.init_state(1), _frames(clips["walk"], 0), w)
    assert state["output_prior/frames"][0, 0] == 1.0
    twin = stateful.with_own_styles()
    twin.stages = twin.stages.without("output_prior")
    twin.step_batch(twin.init_state(1), _frames(clips["walk"], 0), w)
