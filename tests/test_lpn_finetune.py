"""FiLM generator fine-tuning on one clip (models/lpn/finetune.py), on a real clip of a style the
network never saw in training."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.data import load_motion, select
from models.lpn.finetune import FineTuneConfig, fine_tune, min_frames
from models.registry import load_models
from models.settings import get_settings

MODEL = load_models(get_settings().weights_dir)["lpn"]
STEPS = 20


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """As the service runs it (STYLESTREAM_TORCH_THREADS=1); two threads on a busy 2-core box run 3x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def chimpira(index):
    return load_motion(select(index, dataset="bandai-namco-1", style="chimpira", content="walk")[0])


def test_fine_tuning_lowers_the_loss_on_the_clips_held_back_frames_and_leaves_the_network_alone(chimpira):
    net = MODEL.generator()
    original = {k: v.clone() for k, v in net.state_dict().items()}
    seen = []
    res = fine_tune(net, chimpira, FineTuneConfig(steps=STEPS), progress=lambda f, loss: seen.append((f, loss)))

    assert res.heldout_loss_after < 0.9 * res.heldout_loss_before, res.summary()
    assert res.heldout_samples >= 10 and res.fit_samples >= 30
    assert res.film.shape == (4, MODEL.H) and np.isfinite(res.film).all()
    assert np.abs(res.film - res.film_before).max() > 1e-3
    assert [f for f, _ in seen] == pytest.approx([(k + 1) / STEPS for k in range(STEPS)])
    assert all(np.isfinite(loss) for _, loss in seen)
    for k, v in net.state_dict().items():  # a copy was tuned; the served generator is unchanged
        assert torch.equal(v, original[k]), k


def test_fine_tuning_is_deterministic_for_a_seed_and_leaves_the_callers_random_state(chimpira):
    caller = torch.random.get_rng_state()
    runs = [fine_tune(MODEL.generator(), chimpira, FineTuneConfig(steps=3, seed=s)) for s in (7, 7, 8)]
    np.testing.assert_array_equal(runs[0].film, runs[1].film)
    assert not np.array_equal(runs[0].film, runs[2].film)
    assert torch.equal(torch.random.get_rng_state(), caller)


def test_a_clip_too_short_to_hold_frames_back_is_refused(chimpira):
    with pytest.raises(ValueError, match="too short to fine-tune"):
        fine_tune(MODEL.generator(), chimpira.slice(0, min_frames() - 1), FineTuneConfig(steps=1))
    fine_tune(MODEL.generator(), chimpira.slice(0, min_frames()), FineTuneConfig(steps=1))  # the shortest that works
