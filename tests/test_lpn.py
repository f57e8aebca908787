"""LPN-FiLM runtime on the committed weights and real Bandai Namco clips: the numpy step is the
trained torch network, it is causal, control steers it, styles blend and can be added from a clip."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.data import build_index, load_motion, select
from models.interface import FrameBatch, StreamingModel
from models.lpn import features as lf
from models.lpn import load
from models.lpn.dataset import clip_samples
from models.registry import load_models
from models.settings import get_settings

TARGETS = ("normal", "active", "elderly", "exhausted", "feminine", "masculine", "youthful")


@pytest.fixture(scope="module")
def model():
    return load(get_settings().weights_dir / "lpn")


@pytest.fixture(scope="module")
def clips():
    index = build_index(["bandai-namco-1", "bandai-namco-2"])
    walk = load_motion(select(index, dataset="bandai-namco-2", split="val", style="normal", content="walk")[0])
    run = load_motion(select(index, dataset="bandai-namco-2", split="val", style="active", content="run")[0])
    giant = load_motion(select(index, dataset="bandai-namco-1", style="giant", content="walk")[0])
    return {"walk": walk, "run": run, "giant": giant}


def _frames(motion, t: int, control=None) -> FrameBatch:
    return FrameBatch(motion.translations[t:t + 1, 1], motion.rotations[t:t + 1], control=control)


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
    samples = clip_samples(clips["walk"], gait=0.0)
    x, g = samples.X[::7][:16], samples.G[::7][:16]
    film = model.blend_films(np.tile(model.weight_vector({"elderly": 0.7, "active": 0.3}), (len(x), 1)))
    ours = model._network(x, g, film)
    net = model.generator()
    with torch.no_grad():
        theirs = net.denormalise_y(net(net.normalise_x(torch.from_numpy(x)), net.normalise_g(torch.from_numpy(g)),
                                       torch.from_numpy(film))).numpy()
    scale = np.abs(theirs).mean(0) + 1e-3
    assert np.abs((ours - theirs) / scale).max() < 1e-3


def test_step_never_reads_future_frames(model, clips):
    """Two sessions see the same frames up to t = 20, then different clips: outputs agree up to 20."""
    a, b = clips["walk"], clips["run"]
    state = model.init_state(2)
    w = np.tile(model.weight_vector({"elderly": 1.0}), (2, 1))
    outs = []
    for t in range(30):
        second = a if t <= 20 else b
        frames = FrameBatch.concat([_frames(a, t), _frames(second, t)])
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
        out, both = model.step_batch(both, FrameBatch.concat([_frames(walk, t), _frames(run, t)]), w)
        for i, m in enumerate((walk, run)):
            single, alone[i] = model.step_batch(alone[i], _frames(m, t), w[i:i + 1])
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
    e, a, n = (model.film_of(s) for s in ("elderly", "active", "normal"))
    mix = model.blend_films(model.weight_vector({"elderly": 0.5, "active": 0.5})[None])[0]
    np.testing.assert_allclose(mix, 0.5 * (e + a), atol=1e-5)
    half = model.blend_films(model.weight_vector({"elderly": 0.5})[None])[0]
    np.testing.assert_allclose(half, 0.5 * (e + n), atol=1e-5)
    with pytest.raises(ValueError):
        model.blend_films(np.ones((1, 3)))


def test_styles_change_the_motion(model, clips):
    control = np.tile([[1.2, 0.0, 0.0, 0.0, 1.0]], (60, 1))
    paths = {s: model.run(clips["walk"], model.weight_vector({s: 1.0}), control=control)[0] for s in ("normal", "elderly")}
    pose = {s: m.rotations[30:] for s, m in paths.items()}
    assert np.abs(pose["normal"] - pose["elderly"]).mean() > 0.01


def test_add_style_from_clip_gives_a_usable_style_and_remove_drops_it(model, clips):
    model.add_style_from_clip("giant-from-clip", clips["giant"])
    try:
        assert model.styles()[-1] == "giant-from-clip"
        film = model.film_of("giant-from-clip")
        assert np.isfinite(film).all() and not np.allclose(film, model.film_of("normal"), atol=1e-3)
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
