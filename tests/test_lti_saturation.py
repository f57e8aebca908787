"""LTI's systems read the input saturated into their training range and pass the excess through
(`kernels.saturate`), instead of the paper's erf blend handing the whole body back: another
performer's walk (dataset 1, whose clavicles sit outside dataset 2's range on every frame) is
styled, without the extrapolation jitter of the systems reading it raw."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motion, select
from models.interface import FrameBatch
from models.lti import representation as rep
from models.lti.model import LTIStyleModel
from models.motion.rotations import quat_inv, quat_log, quat_mul

from .reference.lti_offline import offline as reference_offline
from .test_lti import _one_hot, _toy_translator

SECONDS = 10


@pytest.fixture(scope="module")
def walks():
    index = build_index(["bandai-namco-1", "bandai-namco-2"])
    d1 = load_motion(select(index, dataset="bandai-namco-1", style="normal", content="walk")[0])
    d2 = load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])
    return {name: m.slice(0, int(SECONDS * m.fps)) for name, m in (("dataset 1", d1), ("dataset 2", d2))}


@pytest.fixture(scope="module")
def models():
    return {"saturated": LTIStyleModel(), "blended": LTIStyleModel(off=("saturation",))}


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.linalg.norm(quat_log(quat_mul(quat_inv(a), b)), axis=-1))


def _p99_acceleration(rotations: np.ndarray) -> float:
    """Degrees per frame per frame over the body joints, as the evaluation's jitter reads it."""
    step = quat_log(quat_mul(quat_inv(rotations[:-1]), rotations[1:]))
    return float(np.percentile(np.degrees(np.linalg.norm(np.diff(step, axis=0), axis=-1))[:, 2:], 99))


def test_saturation_leaves_the_range_alone_and_bounds_what_the_systems_read():
    tr = _toy_translator()  # range [-1, 1] on every DOF, k_p 1
    u = np.linspace(-40.0, 40.0, 8001)[:, None] * np.ones((1, rep.FEATURE_DIM))
    read = tr.saturated(u)
    inside = np.abs(u[:, 0]) <= 1.0
    np.testing.assert_array_equal(read[inside], u[inside])
    assert np.abs(read).max() <= 1.0 + tr.k_p  # never past the blend's tolerance
    assert (np.diff(read[:, 0]) >= 0).all()  # monotone: a larger input never reads smaller
    slope = np.diff(read[:, 0]) / np.diff(u[:, 0])
    assert np.abs(np.diff(slope)).max() < 0.02  # no kink at the range's edge


def test_another_performers_walk_is_styled_not_handed_back(walks, models):
    change = {
        (name, kind): _angles(m.rotations, model.translate(m, "elderly")[0].rotations)[30:, 2:].mean()
        for name, m in walks.items()
        for kind, model in models.items()
    }
    assert change["dataset 1", "saturated"] > 3 * change["dataset 1", "blended"], change
    # the model's own performer lies in range: nothing to saturate
    assert abs(change["dataset 2", "saturated"] - change["dataset 2", "blended"]) < 0.2, change


def test_saturated_the_systems_add_no_jitter_to_another_performer(walks, models):
    walk = walks["dataset 1"]
    out, _ = models["saturated"].translate(walk, "elderly")
    assert _p99_acceleration(out.rotations[30:]) <= _p99_acceleration(walk.rotations[30:])


def test_the_stream_equals_the_offline_reference_where_the_input_saturates(walks, models):
    model, walk = models["saturated"], walks["dataset 1"].slice(0, 90)
    want, contacts = reference_offline(model, "elderly", walk)
    state, w = model.init_state(1), _one_hot(model, "elderly", 1)
    for t in range(walk.num_frames):
        frame = FrameBatch(walk.translations[t : t + 1, rep.HIPS], walk.rotations[t : t + 1])
        out, state = model.step_batch(state, frame, w)
        np.testing.assert_allclose(out.root[0], want.translations[t, rep.HIPS], atol=1e-8)
        np.testing.assert_allclose(out.rotations[0], want.rotations[t], atol=1e-10)
        assert (out.contacts[0] == contacts[t]).all()
