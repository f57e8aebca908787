"""Style-ERD's arm coupling (`models/erd/arm_coupling.py`): running toward feminine and active the
upper arms swing with the thighs as in the real runs, where the run prior had stilled them;
walks, other styles and every other joint stream exactly as without it; offline equals stream."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from models.motion.rotations import quat_inv, quat_mul
from models.motion.style_carry import quat_log

from .clips import streamed_rotations

WEIGHTS = Path(__file__).resolve().parents[1] / "models" / "weights" / "erd"

pytestmark = pytest.mark.skipif(
    not (WEIGHTS / "arm_coupling.npz").exists(), reason="Style-ERD arm coupling not committed"
)


@pytest.fixture(scope="module")
def model():
    import models.erd

    return models.erd.load(WEIGHTS)


@pytest.fixture(scope="module")
def bare(model):
    twin = copy.copy(model)
    twin.arm_coupling = None
    return twin


def _clip(index, content: str, style: str = "normal", split: str = "val", frames: int = 120):
    from models.data import load_motions, select

    clip = select(index, dataset="bandai-namco-2", split=split, style=style, content=content)[0]
    return load_motions([clip])[0].slice(0, frames)


def _weights(model, style: str) -> np.ndarray:
    w = np.zeros(len(model.styles()))
    w[model.styles().index(style)] = 1.0
    return w


def _upper_arms(model) -> list[int]:
    return [model.skeleton.names.index(f"UpperArm_{s}") for s in "LR"]


def _turn_speed(rotations: np.ndarray) -> np.ndarray:
    """Per joint, the mean angular speed (degrees/s at 30 fps) after the first 20 frames."""
    q = rotations[20:].astype(np.float64)
    return np.degrees(np.linalg.norm(quat_log(quat_mul(quat_inv(q[:-1]), q[1:])), axis=-1)).mean(0) * 30


def test_only_runs_toward_feminine_and_active_are_coupled_and_only_the_upper_arms(model, bare, index):
    from models.erd.arm_coupling import COUPLED

    assert model.arm_coupling.styles == COUPLED == ("feminine", "active")  # where validation gained (card)
    run, walk = _clip(index, "run"), _clip(index, "walk")
    for style in ("elderly", "youthful"):
        w = _weights(model, style)
        np.testing.assert_array_equal(streamed_rotations(model, run, w), streamed_rotations(bare, run, w))
    w = _weights(model, "feminine")
    np.testing.assert_array_equal(streamed_rotations(model, walk, w), streamed_rotations(bare, walk, w))
    coupled, plain = streamed_rotations(model, run, w), streamed_rotations(bare, run, w)
    arms = _upper_arms(model)
    others = [j for j in range(model.skeleton.num_joints) if j not in arms]
    np.testing.assert_array_equal(coupled[:, others], plain[:, others])
    assert not np.array_equal(coupled[:, arms], plain[:, arms])


def test_a_feminine_run_swings_its_upper_arms_as_the_real_runs_do(model, bare, index):
    """The run prior left them at less than half the real speed (card); coupled, both upper arms
    turn at least 1.5 times faster and no more than a tenth faster than a real feminine run's."""
    run = _clip(index, "run")
    w = _weights(model, "feminine")
    arms = _upper_arms(model)
    before = _turn_speed(streamed_rotations(bare, run, w)[:, arms])
    after = _turn_speed(streamed_rotations(model, run, w)[:, arms])
    real = _turn_speed(_clip(index, "run", style="feminine", split="train").rotations[:, arms])
    assert np.all(after > 1.5 * before), (before, after)
    assert np.all(after < 1.1 * real), (after, real)


def test_offline_equals_the_stream_on_a_run(model, index):
    from models.erd.offline import stylise

    run = _clip(index, "run", frames=60)
    w = _weights(model, "active")
    streamed = model.stylise_stream(run, w)
    whole = stylise(model.torch_generator(), model.maker, run, w, **model.priors)
    np.testing.assert_allclose(streamed.rotations, whole.rotations, atol=2e-4)
