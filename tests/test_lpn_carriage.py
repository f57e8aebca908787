"""LPN-FiLM's arm carriage (`models/lpn/carriage.py`): a style carries its arms as its real clips
do; styles without real walks (uploads, replaced vectors) get none."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motions, select
from models.lpn.carriage import ARM_JOINTS, Carriage, blend_arms
from models.motion.rotation_ball import comparable
from models.motion.rotations import quat_angle, quat_mean
from tests.lpn_films import film_of, style_table


@pytest.fixture(scope="module")
def model(lpn_model):
    return lpn_model


@pytest.fixture(scope="module")
def walk(bn_walk):
    return bn_walk.slice(0, 150)


def test_the_shipped_carriage_holds_arm_offsets(model):
    c = model.stages.carriage
    every = {"normal", "active", "elderly", "exhausted", "feminine", "masculine", "youthful"}
    assert c is not None and every <= set(c.styles)
    assert quat_angle(c.arms[c.styles.index("active")], np.array([0.0, 0, 0, 1])).max() > np.radians(20)


def test_the_arm_carriage_brings_the_arms_toward_the_real_style(model, walk):
    index = build_index(["bandai-namco-2"])
    real = load_motions([c for c in select(index, split="train", style="feminine") if c.content == "walk"])
    joints = [model.skeleton.names.index(j) for j in ARM_JOINTS]
    mean = quat_mean(comparable(np.concatenate([m.rotations for m in real]))[:, joints], axis=0)
    plain = model.with_own_styles()
    plain.stages = plain.stages.replace(
        carriage=Carriage(model.stages.carriage.styles, np.tile((0.0, 0, 0, 1), (7, 8, 1)))
    )
    apart = {}
    for name, m in (("carried", model), ("bare", plain)):
        out = m.run(walk, m.weight_vector({"feminine": 1.0}))[0]
        apart[name] = np.median(quat_angle(comparable(out.rotations.astype(np.float64))[30:, joints], mean), axis=0)
    lower_arm = ARM_JOINTS.index("LowerArm_L")  # the feminine walk's largest offset (elbow bent ~29 degrees more)
    assert apart["carried"][lower_arm] < apart["bare"][lower_arm] - np.radians(10), np.degrees(apart)
    assert apart["carried"].mean() < apart["bare"].mean()


def test_mixed_weights_blend_the_carriage_with_the_rest_to_normal():
    w = np.array([[0.0, 1.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]])
    half_turn = np.array([0.0, np.sin(0.2), 0.0, np.cos(0.2)])
    arms = np.stack([np.tile((0.0, 0, 0, 1), (8, 1)), np.tile(half_turn, (8, 1)), np.tile((0.0, 0, 0, 1), (8, 1))])
    mixed = blend_arms(arms, w, normal=0)
    np.testing.assert_allclose(mixed[0], arms[1])  # one style at weight 1: its own offset
    assert 0 < quat_angle(mixed[1, 0], arms[1, 0]) < quat_angle(arms[0, 0], arms[1, 0])  # half-way, toward normal
    np.testing.assert_allclose(np.linalg.norm(mixed, axis=-1), 1.0)


def test_uploaded_and_replaced_styles_get_no_carriage(model, walk):
    twin = model.with_own_styles()
    twin.set_style_film("mine", film_of(twin, "active"))
    twin.set_style_film("active", film_of(twin, "active"))  # a built-in's vector replaced: no longer its walks
    arms = style_table(twin).rows["carriage"]["arms"]
    for name in ("mine", "active"):
        assert np.allclose(arms[twin.styles().index(name)], (0, 0, 0, 1))
    k = model.styles().index("active")
    assert not np.allclose(style_table(model).rows["carriage"]["arms"][k], (0, 0, 0, 1))  # the original keeps it
    twin.remove_style("mine")
    assert len(style_table(twin).rows["carriage"]["arms"]) == len(twin.styles())
    out, _ = twin.run(walk, twin.weight_vector({"elderly": 1.0}))
    assert np.isfinite(out.rotations).all()


def test_each_styles_clips_split_into_walks_and_runs_by_their_own_speeds():
    """What every LPN-FiLM stage is fitted on (`carriage.locomotion`): each style's TRAIN clips
    split by their own speeds are exactly its labelled walks and turns, and its runs (elderly's
    runs are slower than active's walks, so no one speed splits them all); gestures are in neither."""
    from models.lpn.carriage import locomotion

    clips = locomotion("bandai-namco-2")
    index = select(build_index(["bandai-namco-2"]), split="train")
    for style in ("elderly", "active"):
        walking, running = clips(style)["walk"], clips(style)["run"]
        labelled = [c for c in index if c.style == style]
        assert len(running) == sum(c.content == "run" for c in labelled)
        assert len(walking) == sum(c.content.startswith("walk") for c in labelled)
