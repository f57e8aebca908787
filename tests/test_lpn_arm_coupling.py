"""LPN-FiLM's arm coupling (`models/lpn/arm_coupling.py`): toward every built-in style the
forearms move with the upper arms, shoulders and chest as in the style's real clips (toward
active they pump where the network held them still); every other joint, and a row with no fitted
style, steps exactly as without it."""

from __future__ import annotations

import numpy as np
import pytest

from models.lpn.arm_coupling import LINKS
from models.motion.coupling import Coupling
from models.motion.rotations import quat_angle, quat_inv, quat_mul
from models.motion.style_carry import quat_log
from tests.lpn_films import film_of, style_table


@pytest.fixture(scope="module")
def model(lpn_model):
    if lpn_model.stages.arm_coupling is None:
        pytest.skip("no LPN-FiLM arm coupling committed")
    return lpn_model


@pytest.fixture(scope="module")
def bare(model):
    twin = model.with_own_styles()
    twin.stages = twin.stages.without("arm_coupling")
    return twin


@pytest.fixture(scope="module")
def walk(bn_walk):
    return bn_walk.slice(0, 150)


def _forearms(model) -> list[int]:
    return [model.skeleton.names.index(f"LowerArm_{s}") for s in "LR"]


def _turn_speed(rotations: np.ndarray) -> float:
    """Mean angular speed (degrees/s at 30 fps) after the first second."""
    q = rotations[30:].astype(np.float64)
    return float(np.degrees(np.linalg.norm(quat_log(quat_mul(quat_inv(q[:-1]), q[1:])), axis=-1)).mean() * 30)


@pytest.mark.parametrize("style", ["active", "elderly", "feminine"])
def test_every_style_is_coupled_and_only_its_forearms_move(model, bare, walk, style):
    assert {"active", "elderly", "exhausted", "feminine", "masculine", "youthful"} <= set(
        model.stages.arm_coupling.styles
    )
    w = model.weight_vector({style: 1.0})
    coupled, plain = model.run(walk, w)[0].rotations, bare.run(walk, w)[0].rotations
    forearms = _forearms(model)
    others = [j for j in range(model.skeleton.num_joints) if j not in forearms]
    np.testing.assert_array_equal(coupled[:, others], plain[:, others])
    assert np.degrees(quat_angle(coupled[:, forearms], plain[:, forearms])).max() > 1.0
    none = np.zeros(len(model.styles()))
    np.testing.assert_array_equal(model.run(walk, none)[0].rotations, bare.run(walk, none)[0].rotations)


def test_active_forearms_pump_faster_toward_the_real_style(model, bare, walk):
    """The network's active forearms turned at less than half the real active speed (model card):
    coupled, both turn faster, and no faster than the real style's."""
    w = model.weight_vector({"active": 1.0})
    coupled, plain = model.run(walk, w)[0].rotations, bare.run(walk, w)[0].rotations
    for j in _forearms(model):
        before, after = _turn_speed(plain[:, j]), _turn_speed(coupled[:, j])
        assert after > 1.1 * before, (model.skeleton.names[j], before, after)
        assert after < 160.0  # the real active forearms: 154-180 degrees/s (model card)


def test_a_mixed_batch_steps_each_row_as_alone(model, walk):
    from models.interface import FrameBatch

    w = np.stack(
        [
            model.weight_vector({"active": 1.0}),
            model.weight_vector({"elderly": 1.0}),
            model.weight_vector({"active": 0.5, "feminine": 0.5}),
        ]
    )
    state, alone = model.init_state(3), [model.init_state(1) for _ in range(3)]
    for t in range(20):
        root = np.repeat(walk.translations[t : t + 1, 1], 3, 0)
        rot = np.repeat(walk.rotations[t : t + 1], 3, 0)
        out, state = model.step_batch(state, FrameBatch(root, rot), w)
        for b in range(3):
            one, alone[b] = model.step_batch(alone[b], FrameBatch(root[b : b + 1], rot[b : b + 1]), w[b : b + 1])
            np.testing.assert_array_equal(out.rotations[b], one.rotations[0])


def test_a_run_takes_the_run_gains_and_a_walk_the_walk_gains(model, walk, index):
    from models.data import load_motions, select

    run = load_motions([select(index, dataset="bandai-namco-2", split="val", style="normal", content="run")[0]])[0]
    c = model.stages.arm_coupling
    once = model.with_own_styles()
    once.stages = once.stages.replace(
        arm_coupling=Coupling(c.styles, c.links, c.mean, c.walk, c.walk)
    )  # walk gains, both gaits
    w = model.weight_vector({"active": 1.0})
    np.testing.assert_array_equal(model.run(walk, w)[0].rotations, once.run(walk, w)[0].rotations)
    forearms = _forearms(model)
    ran, walked = model.run(run.slice(0, 90), w)[0].rotations, once.run(run.slice(0, 90), w)[0].rotations
    assert np.degrees(quat_angle(ran[30:, forearms], walked[30:, forearms])).max() > 2.0


def test_a_replaced_vector_gets_no_coupling_and_the_file_round_trips(model, tmp_path):
    twin = model.with_own_styles()
    twin.set_style_film("active", film_of(twin, "exhausted"))
    assert style_table(twin).rows["arm_coupling"]["on"][twin.styles().index("active")] == 0.0
    assert style_table(model).rows["arm_coupling"]["on"][model.styles().index("active")] == 1.0
    c = model.stages.arm_coupling
    back = Coupling.load(c.save(tmp_path / "coupling.npz"))
    assert back.styles == c.styles and back.links == c.links == LINKS
    for field in ("mean", "walk", "run"):
        np.testing.assert_array_equal(getattr(back, field), getattr(c, field))
    k = c.styles.index("elderly")
    other = Coupling(("elderly",), c.links, c.mean[k : k + 1], c.walk[k : k + 1] * 0.5, c.run[k : k + 1])
    merged = c.with_styles_of(other)
    assert sorted(merged.styles) == sorted(c.styles)
    np.testing.assert_array_equal(merged.walk[merged.styles.index("elderly")], c.walk[k] * 0.5)


def test_the_compiled_coupling_is_the_numpy_reference(model, walk):
    """Mixed weights, gait shares between walk and run, rows without a coupled style."""
    from models.motion.coupling import link_indices
    from models.stages import StageFrame
    from tests.reference.coupling import couple_numpy

    rng = np.random.default_rng(0)
    rot = np.repeat(walk.rotations[:40], 2, axis=0).astype(np.float32)
    rot = rot * rng.choice([-1.0, 1.0], size=rot.shape[:2] + (1,)).astype(np.float32)  # either sign
    w = np.zeros((len(rot), len(model.styles())))
    active, elderly = model.styles().index("active"), model.styles().index("elderly")
    w[:, active] = rng.choice([0.0, 0.3, 1.0, 1.4], len(rot))
    w[:, elderly] = rng.choice([0.0, 0.7], len(rot))
    gait = rng.choice([0.0, 0.4, 1.0], len(rot))
    joints, rows = link_indices(LINKS, model.skeleton.names), style_table(model).rows["arm_coupling"]
    frame = StageFrame(rot, w, gait, model.styles().index("normal"))
    compiled, reference = (
        model.stages.arm_coupling.step_batch({}, frame, rows)[0],
        couple_numpy(rot, w, gait, joints, rows),
    )
    assert compiled.dtype == rot.dtype
    bare = (w[:, active] == 0) & (w[:, elderly] == 0)
    np.testing.assert_array_equal(compiled[bare], rot[bare])
    np.testing.assert_allclose(compiled, reference, atol=1e-6)  # float32 outputs: an ulp or two
