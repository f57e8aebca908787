"""Snapshot selection (`tools/lpn_snapshots.py`): the live-unit share must tell a dead FiLM
generator from a live one, and the validation inputs must come from the validation split."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from models.lpn import features as lf
from models.lpn.network import LPN, LPNConfig
from tools.lpn_snapshots import Options, live_units, pace, validation_inputs


def test_a_generator_driven_below_the_elu_floor_has_no_live_units():
    torch.manual_seed(0)
    windows = np.random.default_rng(0).normal(size=(4, 120, lf.STYLE_DIM)).astype(np.float32)
    net = LPN(LPNConfig(hidden=16, filters=32))
    live, _ = live_units(net, windows)
    assert live > 0.5
    with torch.no_grad():
        net.film.conv2.bias.fill_(-50.0)  # what training did to the committed generator's units
    assert live_units(net, windows) == (0.0, 0.0)
    net.film.norm = True  # film_norm: the units are normalised over the filters first
    assert live_units(net, windows)[0] > 0.5


def test_inputs_are_validation_neutral_clips_over_every_content():
    inputs, contents = validation_inputs(Options(clips=10, frames=30))
    assert len(inputs) == 10 and len(set(contents)) == 10
    assert all(m.num_frames <= 30 for m in inputs)


def test_pace_is_one_for_the_input_itself_and_zero_for_a_motion_that_stays_put(bn_walk):
    walk = bn_walk.slice(0, 90)
    trans = walk.translations.copy()
    trans[:, 1] = trans[0, 1]  # the hips never leave their first position
    stays_put = replace(walk, translations=trans)
    assert pace([walk], [walk]) == 1.0
    assert pace([stays_put], [walk]) == 0.0
