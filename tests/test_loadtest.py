"""The open-loop load test against a real server: every frame sent gets its reply and is counted
once, clocks are spread or aligned as asked and start only once every session is connected (a
slow client start must not turn into a burst of overdue frames), and a client process that
fails says why instead of leaving the harness waiting for it."""

from __future__ import annotations

import numpy as np
import pytest

from clients.loadtest import clock_offsets, run
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server


@pytest.fixture(scope="module")
def server():
    models = {"lti": load_models(get_settings().weights_dir)["lti"]}
    with live_server(models) as (base, _):
        yield base.replace("http", "ws", 1) + "/v1/stream", models["lti"].styles()[0]


def test_spread_clocks_cover_one_period_evenly_and_aligned_ones_start_together():
    assert np.allclose(clock_offsets(4, 60.0), [0, 1 / 240, 2 / 240, 3 / 240])
    assert clock_offsets(3, 60.0, "aligned") == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="phase"):
        clock_offsets(3, 60.0, "random")


@pytest.mark.parametrize("phase", ["spread", "aligned"])
def test_every_frame_of_every_session_gets_its_reply(server, phase):
    url, style = server
    result, latency = run(url, sessions=3, fps=60.0, seconds=1.0, model="lti", style=style, processes=2, phase=phase)
    assert result.sent == 3 * 60 == len(latency)
    assert result.received == result.sent and result.lost == 0 and result.dropped == 0
    assert result.client_processes == 2 and result.phase == phase
    assert np.isfinite(latency).all() and (latency > 0).all()
    assert 0 < result.p50_ms <= result.p99_ms <= result.max_ms < 1000
    assert result.client_cpu_s > 0


def test_a_refused_session_fails_the_run_with_the_servers_reason(server, mocap_data):
    url, _ = server
    with pytest.raises(RuntimeError, match="session refused.*unknown_model"):
        run(url, sessions=2, fps=60.0, seconds=0.5, model="no-such-model", style="x", processes=2)


def test_crowds_count_every_characters_frame(server):
    """`--characters 5`: two crowd connections of five characters; every count is in
    character-frames, one latency per tick."""
    url, style = server
    result, latency = run(url, sessions=2, fps=60.0, seconds=1.0, model="lti", style=style, processes=1, characters=5)
    assert len(latency) == 2 * 60 and result.characters == 5
    assert result.sent == 2 * 60 * 5 == result.received and result.lost == 0 and result.dropped == 0
    assert result.frames_per_s == pytest.approx(600.0)
    assert np.isfinite(latency).all()
