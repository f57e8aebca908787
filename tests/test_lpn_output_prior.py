"""LPN-FiLM's output prior (`models/lpn/output_prior.py`): every built-in style's upper body is
carried to the style's real rotations and kept in its real range, by a prior fitted on its walks
and one on its runs; the legs, the Hips, and a row with no fitted style, step exactly as without it."""

from __future__ import annotations

import numpy as np
import pytest

from models.lpn.carriage import UPPER_BODY
from models.lpn.output_prior import CARRIED, OutputPrior
from models.motion.feet import LEG_JOINTS
from models.motion.rotations import quat_angle, quat_inv, quat_mul
from tests.lpn_films import film_of, style_table


@pytest.fixture(scope="module")
def model(lpn_model):
    if lpn_model.stages.output_prior is None:
        pytest.skip("no LPN-FiLM output prior committed")
    return lpn_model


@pytest.fixture(scope="module")
def walk(bn_walk):
    return bn_walk.slice(0, 90)


def _without(model):
    bare = model.with_own_styles()
    bare.stages = bare.stages.without("output_prior")
    return bare


def test_every_style_carries_the_same_joints(model):
    """Every fitted style, walking and running, carries `CARRIED` and nothing else: the legs and Hips never."""
    names = model.skeleton.names
    for carry in (model.stages.output_prior.carry, model.stages.output_prior.run):
        for k, style in enumerate(model.stages.output_prior.styles):
            carried = {names[j] for j in np.flatnonzero(carry.radius[k] < np.pi)}
            assert carried == set(CARRIED), style
    assert not set(LEG_JOINTS) & set(CARRIED) and set(UPPER_BODY) == set(CARRIED)


def test_every_dataset_2_style_has_a_prior_and_only_the_carried_joints_move(model, walk):
    bare = _without(model)
    assert {"active", "elderly", "exhausted", "feminine", "masculine", "youthful"} <= set(
        model.stages.output_prior.styles
    )
    for style in ("elderly", "feminine"):
        w = model.weight_vector({style: 1.0})
        carried, plain = model.run(walk, w)[0].rotations, bare.run(walk, w)[0].rotations
        upper = [model.skeleton.names.index(j) for j in UPPER_BODY]
        assert np.degrees(quat_angle(carried[:, upper], plain[:, upper])).max() > 2.0
        # never the Hips or the root joint
        np.testing.assert_array_equal(carried[:, :2], plain[:, :2])


def test_carried_joints_stay_inside_the_styles_real_range(model, walk):
    prior = model.stages.output_prior.carry
    k = model.stages.output_prior.styles.index("active")
    out = model.run(walk, model.weight_vector({"active": 1.0}))[0].rotations.astype(np.float64)
    for name in UPPER_BODY:
        j = model.skeleton.names.index(name)
        angle = quat_angle(quat_mul(quat_inv(prior.mean[k, j])[None], out[:, j]), np.array([0.0, 0, 0, 1]))
        assert np.all(angle <= prior.radius[k, j] + 1e-4), name  # float32 output


def test_a_mixed_batch_steps_each_row_as_alone(model, walk):
    from models.interface import FrameBatch

    w = np.stack([model.weight_vector({"active": 1.0}), model.weight_vector({"elderly": 1.0})])
    w = np.concatenate([w, model.weight_vector({"active": 0.5, "exhausted": 0.5})[None]])
    state, alone = model.init_state(3), [model.init_state(1) for _ in range(3)]
    for t in range(20):
        root = np.repeat(walk.translations[t : t + 1, 1], 3, 0)
        rot = np.repeat(walk.rotations[t : t + 1], 3, 0)
        out, state = model.step_batch(state, FrameBatch(root, rot), w)
        for b in range(3):
            one, alone[b] = model.step_batch(alone[b], FrameBatch(root[b : b + 1], rot[b : b + 1]), w[b : b + 1])
            np.testing.assert_array_equal(out.rotations[b], one.rotations[0])


def test_a_replaced_vector_gets_no_prior_and_the_file_round_trips(model, tmp_path):
    twin = model.with_own_styles()
    twin.set_style_film("active", film_of(twin, "exhausted"))
    assert style_table(twin).rows["output_prior"]["on"][twin.styles().index("active")] == 0.0
    assert style_table(model).rows["output_prior"]["on"][model.styles().index("active")] == 1.0
    back = OutputPrior.load(model.stages.output_prior.save(tmp_path / "prior.npz"))
    assert back.styles == model.stages.output_prior.styles
    np.testing.assert_array_equal(back.carry.map, model.stages.output_prior.carry.map)
    np.testing.assert_array_equal(back.run.map, model.stages.output_prior.run.map)


@pytest.fixture(scope="module")
def run(index):
    from models.data import load_motions, select

    clip = select(index, dataset="bandai-namco-2", split="val", style="normal", content="run")[0]
    return load_motions([clip])[0].slice(0, 90)


def _table_without_run_prior(model):
    """A copy whose run prior rows are its walk prior's: every style fitted once."""
    from models.lpn.output_prior import OutputPrior

    bare = model.with_own_styles()
    prior = model.stages.output_prior
    bare.stages = bare.stages.replace(output_prior=OutputPrior(prior.styles, prior.carry, prior.carry))
    return bare


@pytest.mark.parametrize("style", ["active", "elderly"])
def test_runs_take_their_own_prior_and_walks_the_walk_prior(model, walk, run, style):
    """Each style's prior is fitted on walks and on runs apart, mixed by the gait: a walk is
    carried exactly as by the walk prior alone; a run moves."""
    once = _table_without_run_prior(model)
    upper = [model.skeleton.names.index(j) for j in UPPER_BODY]
    w = model.weight_vector({style: 1.0})
    np.testing.assert_array_equal(model.run(walk, w)[0].rotations, once.run(walk, w)[0].rotations)
    moved = np.degrees(
        quat_angle(model.run(run, w)[0].rotations[30:, upper], once.run(run, w)[0].rotations[30:, upper])
    )
    assert np.median(moved.max(axis=-1)) > 2.0


def test_a_refit_of_some_styles_keeps_the_others_and_an_older_file_has_one_prior(model, tmp_path):
    """`python -m models.lpn fit --stages output_prior active` refits active alone (`with_styles_of`); a file
    written before the run prior existed loads with each style's one prior for both gaits."""
    from models.motion.style_carry import StyleCarry

    prior = model.stages.output_prior
    c = prior.carry
    path = tmp_path / "old.npz"
    np.savez(path, styles=np.array(prior.styles), source=c.source, mean=c.mean, map=c.map, radius=c.radius)
    old = OutputPrior.load(path)
    np.testing.assert_array_equal(old.run.map, old.carry.map)
    k = prior.styles.index("active")
    refit = StyleCarry(*(a[k : k + 1] for a in prior.run.arrays))
    merged = old.with_styles_of(OutputPrior(("active",), refit, refit))
    assert sorted(merged.styles) == sorted(prior.styles)
    e, a = merged.styles.index("exhausted"), merged.styles.index("active")
    np.testing.assert_array_equal(merged.carry.map[e], c.map[prior.styles.index("exhausted")])
    np.testing.assert_array_equal(merged.carry.map[a], prior.run.map[k])


def test_an_axis_the_source_keeps_still_is_not_stretched_past_the_floor():
    """A source that never twists about x, toward a style that does: without a floor the map
    stretches x by the style's spread over numerical noise; with one, by at most spread / floor."""
    from models.lpn.output_prior import SOURCE_FLOOR_DEG
    from models.motion.rotations import quat_exp
    from models.motion.style_carry import StyleCarry

    rng = np.random.default_rng(0)
    still = rng.normal(0, 0.2, (5000, 1, 3)) * [0.0, 1.0, 1.0]
    spread = rng.normal(0, 0.2, (5000, 1, 3))
    source, target = quat_exp(still), quat_exp(spread)
    floor = np.radians(SOURCE_FLOOR_DEG)
    gain = lambda carry: np.linalg.svd(carry.map[0, 0], compute_uv=False)[0]  # noqa: E731
    assert gain(StyleCarry.fit([source], [target])) > 100
    assert gain(StyleCarry.fit([source], [target], source_floor=floor)) <= 0.2 * 1.05 / floor
