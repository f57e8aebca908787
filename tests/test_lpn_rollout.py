"""Closed-loop rollouts (`models/lpn/rollout.py`): a network that predicts the recording exactly must
be fed back the recording's own inputs, so every difference a real network sees comes from its
own mistakes and not from the bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.data import build_index, load_motion, select
from models.lpn import features as lf
from models.lpn.dataset import clip_samples
from models.lpn.rollout import rollout, rollout_starts


class Replay(torch.nn.Module):
    """Stands in for the network: predicts the recorded next frame and keeps what it was fed."""

    def __init__(self, Y: torch.Tensor):
        super().__init__()
        self.Y, self.k, self.seen = Y, 0, []
        self.register_buffer("X_mean", torch.zeros(lf.X_DIM))

    normalise_x = normalise_g = normalise_y = denormalise_y = staticmethod(lambda a: a)

    def forward(self, x, g, film):
        self.seen.append((x.clone(), g.clone()))
        out = self.Y[:, self.k]
        self.k += 1
        return out


@pytest.fixture(scope="module")
def samples():
    index = build_index(["bandai-namco-2"])
    clip = select(index, split="val", style="normal", content="walk-turn-left")[0]
    s = clip_samples(load_motion(clip), gait=0.0)
    return torch.from_numpy(s.X), torch.from_numpy(s.G), torch.from_numpy(s.Y)


@pytest.mark.parametrize("first", [0, 3, 40])
def test_an_exact_network_is_fed_back_the_recorded_inputs(samples, first):
    X, G, Y = samples
    K = 12
    idx = torch.arange(first, first + K)[None]
    net = Replay(Y[idx])
    rollout(net, X[idx], G[idx], Y[idx], torch.zeros(1, 4, 8), torch.ones(1, dtype=torch.bool))
    for k, (x, g) in enumerate(net.seen):
        want_x, want_g = X[first + k], G[first + k]
        # trajectory and pose: the root track and the fed-back pose reproduce them
        assert torch.allclose(x[0, lf.TRAJ_IN], want_x[lf.TRAJ_IN], atol=0.05), k
        assert torch.allclose(x[0, lf.POSE_IN], want_x[lf.POSE_IN], atol=1e-4), k
        # phases: the runtime's update (advance by frequency, blend with the prediction) follows them
        assert np.corrcoef(g[0].numpy(), want_g.numpy())[0, 1] > 0.98, k


def test_teacher_forced_rollouts_see_only_the_recording(samples):
    X, G, Y = samples
    idx = torch.arange(5, 13)[None]
    net = Replay(Y[idx] + 3.0)  # wrong predictions must not leak into a teacher-forced rollout
    rollout(net, X[idx], G[idx], Y[idx], torch.zeros(1, 4, 8), torch.zeros(1, dtype=torch.bool))
    for k, (x, g) in enumerate(net.seen):
        assert torch.equal(x[0], X[5 + k]) and torch.equal(g[0], G[5 + k])


def test_rollouts_start_only_where_a_clip_has_the_frames():
    clip = np.array([0, 0, 0, 1, 1, 1, 1, 2])
    style = np.array([0, 0, 0, 1, 1, 1, 1, 1])
    starts = rollout_starts(clip, style, 3)
    assert starts[0].tolist() == [0] and starts[1].tolist() == [3, 4]
