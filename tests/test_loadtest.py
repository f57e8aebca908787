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
    # a loaded machine may answer some ticks with a drop count instead of a frame; none goes unanswered
    assert result.received + result.dropped == result.sent and result.lost == 0
    assert result.client_processes == 2 and result.phase == phase
    answered = np.isfinite(latency)  # a dropped frame has no latency
    assert answered.sum() == result.received and (latency[answered] > 0).all()
    assert 0 < result.p50_ms <= result.p99_ms <= result.max_ms
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
    assert result.sent == 2 * 60 * 5 == result.received + result.dropped and result.lost == 0
    assert result.frames_per_s == pytest.approx(result.received)  # over one second
    assert np.isfinite(latency).all()


@pytest.fixture
def late_echo():
    """An echo server that answers every message `LATE_S` after it arrived (without holding up the
    ones behind it): a server that has fallen that far behind."""
    import asyncio
    import threading

    from websockets.asyncio.server import serve

    loop = asyncio.new_event_loop()
    ready: dict = {}

    async def echo_late(ws) -> None:
        async def answer(message) -> None:
            await asyncio.sleep(LATE_S)
            await ws.send(message)

        tasks = set()
        async for message in ws:
            task = asyncio.create_task(answer(message))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
        await asyncio.gather(*tasks, return_exceptions=True)

    async def main() -> None:
        async with serve(echo_late, "127.0.0.1", 0) as server:
            ready["port"] = server.sockets[0].getsockname()[1]
            ready["stop"] = loop.create_future()
            started.set()
            await ready["stop"]

    started = threading.Event()
    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    thread.start()
    assert started.wait(30)
    yield f"ws://127.0.0.1:{ready['port']}/v1/stream"
    loop.call_soon_threadsafe(ready["stop"].set_result, None)
    thread.join(30)


LATE_S = 0.8  # longer than the half second the load test used to wait after its last frame


def test_replies_still_due_after_the_last_frame_are_late_not_lost(late_echo, mocap_data):
    """A server 0.8 s behind: every reply arrives after the session's last frame went out; the
    run waits for them (it counts what it never gets as lost) and counts them late."""
    result, latency = run(late_echo, sessions=2, fps=30.0, seconds=0.5, processes=1, echo=True)
    assert result.sent == 2 * 15 == result.received and result.lost == 0
    assert result.late == result.sent and np.nanmin(latency) >= 1000.0 * LATE_S
