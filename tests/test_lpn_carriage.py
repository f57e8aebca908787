"""LPN-FiLM's arm carriage and optional pace (`models/lpn/carriage.py`): a style carries its arms
as its real clips do; paced, it walks at its own pace when driven by a walk, while a control the
caller gives is kept; styles without real walks (uploads, replaced vectors) get neither."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motions, select
from models.lpn.carriage import ARM_JOINTS, Carriage, blend_arms, blend_pace
from models.motion.rotation_ball import comparable
from models.motion.rotations import quat_angle, quat_mean


@pytest.fixture(scope="module")
def model(lpn_model):
    return lpn_model


@pytest.fixture(scope="module")
def walk(bn_walk):
    return bn_walk.slice(0, 150)


def speed(motion, skip: int = 30) -> float:
    """Median horizontal Hips speed (cm/s) after the first second."""
    xz = motion.translations[skip:, 1][:, [0, 2]]
    return float(np.median(np.linalg.norm(np.diff(xz, axis=0), axis=1)) * motion.fps)


def paced(model, pace: dict[str, tuple[float, float]]):
    """The model with the shipped arm carriage and these styles' (walk, run) paces."""
    c = model.carriage
    twin = model.with_own_styles()
    twin.carriage = Carriage(c.styles, np.array([pace.get(s, (1.0, 1.0)) for s in c.styles]), c.arms)
    return twin


def test_the_shipped_carriage_holds_arm_offsets_and_no_pace(model):
    c = model.carriage
    every = {"normal", "active", "elderly", "exhausted", "feminine", "masculine", "youthful"}
    assert c is not None and every <= set(c.styles)
    assert (c.pace == 1.0).all()  # pace is opt-in (carriage.py)
    assert quat_angle(c.arms[c.styles.index("active")], np.array([0.0, 0, 0, 1])).max() > np.radians(20)


def test_a_paced_style_driven_by_a_walk_walks_at_its_pace(model, walk):
    twin = paced(model, {"active": (1.3, 1.25), "elderly": (0.7, 0.5)})
    got = {s: speed(twin.run(walk, twin.weight_vector({s: 1.0}))[0]) for s in ("normal", "active", "elderly")}
    assert got["active"] / got["normal"] == pytest.approx(1.3, rel=0.15), got
    assert got["elderly"] / got["normal"] == pytest.approx(0.7, rel=0.15), got
    unpaced = speed(model.run(walk, model.weight_vector({"active": 1.0}))[0])
    assert got["active"] > 1.15 * unpaced  # the shipped model walks at the input's speed


def test_a_control_the_caller_gives_is_not_paced(model, walk):
    """A game that steers the character sets its speed: the root moves as without the carriage."""
    control = np.tile(np.array([1.2, 0.0, 0.0, 0.0, 1.0], np.float32), (walk.num_frames, 1))  # 1.2 m/s ahead
    plain, twin = model.with_own_styles(), paced(model, {"active": (1.3, 1.25), "elderly": (0.7, 0.5)})
    plain.carriage = None
    for style in ("active", "elderly"):
        carried = twin.run(walk, twin.weight_vector({style: 1.0}), control=control)[0]
        bare = plain.run(walk, plain.weight_vector({style: 1.0}), control=control)[0]
        np.testing.assert_array_equal(carried.translations, bare.translations)


def test_the_arm_carriage_brings_the_arms_toward_the_real_style(model, walk):
    index = build_index(["bandai-namco-2"])
    real = load_motions([c for c in select(index, split="train", style="feminine") if c.content == "walk"])
    joints = [model.skeleton.names.index(j) for j in ARM_JOINTS]
    mean = quat_mean(comparable(np.concatenate([m.rotations for m in real]))[:, joints], axis=0)
    plain = model.with_own_styles()
    plain.carriage = Carriage(model.carriage.styles, model.carriage.pace, np.tile((0.0, 0, 0, 1), (7, 8, 1)))
    apart = {}
    for name, m in (("carried", model), ("bare", plain)):
        out = m.run(walk, m.weight_vector({"feminine": 1.0}))[0]
        apart[name] = np.median(quat_angle(comparable(out.rotations.astype(np.float64))[30:, joints], mean), axis=0)
    lower_arm = ARM_JOINTS.index("LowerArm_L")  # the feminine walk's largest offset (elbow bent ~29 degrees more)
    assert apart["carried"][lower_arm] < apart["bare"][lower_arm] - np.radians(10), np.degrees(apart)
    assert apart["carried"].mean() < apart["bare"].mean()


def test_mixed_weights_blend_pace_and_carriage_with_the_rest_to_normal():
    pace = np.array([[1.0, 1.0], [1.3, 1.2], [0.7, 0.5]])
    w = np.array([[0.0, 1.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]])
    got = blend_pace(pace, w, np.array([0.0, 0.0, 1.0, 1.0]))
    np.testing.assert_allclose(got, [1.3, 1.15, 0.85, 0.5])
    half_turn = np.array([0.0, np.sin(0.2), 0.0, np.cos(0.2)])
    arms = np.stack([np.tile((0.0, 0, 0, 1), (8, 1)), np.tile(half_turn, (8, 1)), np.tile((0.0, 0, 0, 1), (8, 1))])
    mixed = blend_arms(arms, w, normal=0)
    np.testing.assert_allclose(mixed[0], arms[1])  # one style at weight 1: its own offset
    assert 0 < quat_angle(mixed[1, 0], arms[1, 0]) < quat_angle(arms[0, 0], arms[1, 0])  # half-way, toward normal
    np.testing.assert_allclose(np.linalg.norm(mixed, axis=-1), 1.0)


def test_uploaded_and_replaced_styles_get_no_pace_or_carriage(model, walk):
    twin = paced(model, {"active": (1.3, 1.25)})
    twin.set_style_film("mine", twin.film_of("active"))
    twin.set_style_film("active", twin.film_of("active"))  # a built-in's vector replaced: no longer its walks
    pace, arms = twin.style_table.get("pace"), twin.style_table.get("arms")
    for name in ("mine", "active"):
        k = twin.styles().index(name)
        assert (pace[k] == 1.0).all() and np.allclose(arms[k], (0, 0, 0, 1))
    k = model.styles().index("active")
    assert not np.allclose(model.style_table.get("arms")[k], (0, 0, 0, 1))  # the original keeps it
    twin.remove_style("mine")
    assert len(twin.style_table.get("pace")) == len(twin.style_table.get("arms")) == len(twin.styles())
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
