"""Joint coupling (`models/motion/coupling.py`) on synthetic rotations: a fit gives the model's
joints the real relation to their drivers, links apply in order, the compiled step is the
numpy reference, and rows without a coupled style are untouched."""

from __future__ import annotations

import numpy as np
import pytest

from models.motion.coupling import Coupling, couple, deviations, link_indices, regression
from models.motion.rotations import quat_exp
from tests.reference.coupling import couple_numpy

NAMES = ("Hips", "Thigh", "Arm", "Forearm")
LINKS = (("Arm", ("Hips", "Thigh")), ("Forearm", ("Arm",)))


def _clips(gain_arm: float, gain_forearm: float, seed: int, frames: int = 600) -> list[np.ndarray]:
    """Rotations (F, 4, 4): the hips and thigh swing; the arm follows the thigh by `gain_arm`, the
    forearm the arm by `gain_forearm`, each with a little noise of its own."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 30.0
    v = np.zeros((frames, 4, 3))
    v[:, 0, 1] = 0.1 * np.sin(2 * np.pi * t)
    v[:, 1, 0] = 0.5 * np.sin(2 * np.pi * 1.3 * t)
    v[:, 2, 0] = gain_arm * v[:, 1, 0] + rng.normal(0, 0.02, frames)
    v[:, 3, 2] = gain_forearm * v[:, 2, 0] + rng.normal(0, 0.02, frames)
    return [quat_exp(v)]


@pytest.fixture(scope="module")
def fitted() -> Coupling:
    real = {"walk": _clips(-0.8, 1.5, 0), "run": _clips(-1.2, 1.0, 1)}
    made = {"walk": _clips(-0.1, 0.0, 2), "run": _clips(-0.1, 0.0, 3)}
    return Coupling.fit(["s"], LINKS, NAMES, lambda s, g: real[g], lambda s, g: made[g])


def _coupled(coupling: Coupling, q: np.ndarray, share: float) -> np.ndarray:
    weights = np.ones((len(q), 1))
    return couple(q, weights, np.full(len(q), share), link_indices(LINKS, NAMES), coupling.aligned(["s"]))


@pytest.mark.parametrize(("gait", "share", "arm", "forearm"), [("walk", 0.0, -0.8, 1.5), ("run", 1.0, -1.2, 1.0)])
def test_the_models_joints_take_the_real_relation_to_their_drivers(fitted, gait, share, arm, forearm):
    made = _clips(-0.1, 0.0, 7)[0]
    out = _coupled(fitted, made, share)
    mean = fitted.mean[0]
    targets, drivers = link_indices(LINKS, NAMES)
    before_arm = regression(made, mean, targets[0], drivers[0])
    after_arm, after_forearm = (regression(out, mean, t, d) for t, d in zip(targets, drivers))
    assert abs(before_arm[3, 0] - arm) > 0.5  # the thigh's x -> the arm's x, before
    assert after_arm[3, 0] == pytest.approx(arm, abs=0.05)
    assert after_forearm[0, 2] == pytest.approx(forearm, abs=0.05)  # read from the moved arm
    d = deviations(out[:, :2], mean[:2])
    np.testing.assert_array_equal(out[:, :2], made[:, :2])  # the drivers stay
    assert np.isfinite(d).all()


def test_the_compiled_step_is_the_numpy_reference_and_leaves_other_rows_alone(fitted):
    rng = np.random.default_rng(3)
    q = _clips(-0.3, 0.4, 9, frames=50)[0] * rng.choice([-1.0, 1.0], (50, 4, 1))
    weights = rng.choice([0.0, 0.4, 1.0, 1.3], (50, 1))
    share = rng.choice([0.0, 0.5, 1.0], 50)
    joints, aligned = link_indices(LINKS, NAMES), fitted.aligned(["s"])
    compiled, reference = couple(q, weights, share, joints, aligned), couple_numpy(q, weights, share, joints, aligned)
    np.testing.assert_allclose(compiled, reference, atol=1e-12)
    still = weights[:, 0] == 0.0
    np.testing.assert_array_equal(compiled[still], q[still])


def test_a_style_without_a_coupling_is_not_touched_and_files_round_trip(fitted, tmp_path):
    aligned = fitted.aligned(["other", "s"])
    assert aligned["on"].tolist() == [0.0, 1.0] and not aligned["walk"][0].any()
    q = _clips(-0.3, 0.4, 5, frames=20)[0]
    out = couple(q, np.tile([1.0, 0.0], (20, 1)), np.zeros(20), link_indices(LINKS, NAMES), aligned)
    assert out is q
    back = Coupling.load(fitted.save(tmp_path / "c.npz"))
    assert back.styles == fitted.styles and back.links == fitted.links
    np.testing.assert_array_equal(back.run, fitted.run)
    with pytest.raises(ValueError, match="different links"):
        fitted.with_styles_of(Coupling(("t",), LINKS[:1], fitted.mean, fitted.walk[:, :1], fitted.run[:, :1]))
