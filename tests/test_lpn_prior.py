"""LPN-FiLM's rotation prior (`rotation_prior.npz`, `models.motion.rotation_ball`): streamed output
stays inside each style's ball; mixed weights blend the balls; uploaded styles are not clamped."""

from __future__ import annotations

import numpy as np
import pytest

from models.lpn.runtime import LPNModel
from models.motion.feet import LEGS
from models.motion.rotation_ball import comparable
from models.motion.rotation_ball_kernels import clamp_mixed
from models.motion.rotations import quat_angle
from models.settings import get_settings
from tests.lpn_films import film_of, style_table
from tests.reference.rotation_ball import clamp_rotations


@pytest.fixture(scope="module")
def model(lpn_model):
    return lpn_model


@pytest.fixture(scope="module")
def walk(bn_walk):
    return bn_walk.slice(0, 90)


def _beyond(model, motion, style: str) -> np.ndarray:
    """(T, J) angle past the style's outer radius (radians, <= 0 inside) of each joint the foot
    planter does not re-pose (it runs after the prior and moves only the legs)."""
    k = model.stages.rotation_balls.styles.index(style)
    mean, radii = model.stages.rotation_balls.mean[k], model.stages.rotation_balls.radii[k]
    keep = [j for j in range(1, 22) if model.skeleton.names[j] not in sum(LEGS, ())]
    angle = quat_angle(comparable(motion.rotations.astype(np.float64)), mean)
    return (angle - radii[1])[:, keep]


def test_streamed_output_stays_inside_the_ball(model, walk):
    bare = LPNModel(model.p, model.skeleton, model.config)  # the same network without the prior
    left = []
    for style in ("elderly", "exhausted", "feminine", "masculine"):
        out, _ = model.run(walk, model.weight_vector({style: 1.0}))
        assert _beyond(model, out, style).max() < 1e-3, style  # float32 output: round-off only
        loose, _ = bare.run(walk, bare.weight_vector({style: 1.0}))
        left.append((_beyond(model, loose, style) > 0).mean())
    # the network alone does leave the ball (feminine: its shoulders, masculine: its spine; the
    # spine flips that took exhausted out of it are re-split, `_untwist`)
    assert max(left) > 0.01


def test_mixed_weights_blend_each_styles_clamp(model, walk):
    """One style at weight 1: exactly its ball (the numpy map); a mix: the normalised weighted
    mean of each style's clamped rotation, the shortfall from 1 going to `normal`."""
    q = walk.rotations.astype(np.float64)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)  # stored in float32: arccos would magnify that
    rows = model.stages.rotation_balls.rows(model.styles(), model.skeleton)
    mean, radii = rows["mean"], rows["radii"]
    e, x, n = (model.styles().index(s) for s in ("elderly", "exhausted", "normal"))
    w = np.zeros((len(q), len(model.styles())))
    w[:, e] = 1.0
    out = np.empty_like(q)
    clamp_mixed(q, w, n, mean, radii, out)
    assert quat_angle(out, clamp_rotations(q, mean[e], radii[e])).max() < 1e-6
    w[:, e], w[:, x] = 0.5, 0.3
    clamp_mixed(q, w, n, mean, radii, out)
    parts = [clamp_rotations(q, mean[s], radii[s]) for s in (e, x, n)]
    signs = [np.sign(np.sum(p * parts[0], -1, keepdims=True)) for p in parts]
    want = sum(k * s * p for k, s, p in zip((0.5, 0.3, 0.2), signs, parts))
    want /= np.linalg.norm(want, axis=-1, keepdims=True)
    assert quat_angle(out[:, 1:], want[:, 1:]).max() < 1e-6


def test_uploaded_styles_are_not_clamped(model, walk):
    twin = model.with_own_styles()
    twin.set_style_film("mine", film_of(twin, "elderly"))
    twin.set_style_film("elderly", film_of(twin, "elderly"))  # a built-in's vector replaced: no longer its data
    radii = style_table(twin).rows["rotation_balls"]["radii"]
    for name in ("mine", "elderly"):
        assert np.isinf(radii[twin.styles().index(name)]).all()
    assert np.isfinite(radii[twin.styles().index("exhausted"), :, 1:]).all()
    original = style_table(model).rows["rotation_balls"]["radii"][model.styles().index("elderly")]
    assert np.isfinite(original[:, 1:]).all()  # the original keeps it
    twin.remove_style("mine")
    assert (
        len(style_table(twin).rows["rotation_balls"]["mean"])
        == len(style_table(twin).rows["rotation_balls"]["radii"])
        == len(twin.styles())
    )
    out, _ = twin.run(walk, twin.weight_vector({"elderly": 1.0}))
    assert np.isfinite(out.rotations).all()


def test_tuned_builtin_styles_keep_their_prior(model):
    """The built-in vectors tuned on their own clips (`tuned_film.npz`) are what the model loads,
    and those styles are still clamped by their balls (unlike a vector set at run time)."""
    from models.lpn.weights import TUNED_FILE, read_weights

    folder = get_settings().weights_dir / "lpn"
    with np.load(folder / TUNED_FILE) as z:
        tuned = dict(zip((str(n) for n in z["styles"]), z["film"]))
    assert tuned, "no tuned built-in styles"
    exported, _, _ = read_weights(folder, tuned=False)
    for name, film in tuned.items():
        k = model.styles().index(name)
        assert np.array_equal(film_of(model, name), film)
        assert not np.array_equal(exported["style_film"][k], film)
        assert np.isfinite(style_table(model).rows["rotation_balls"]["radii"][k, :, 1:]).all(), name
