"""The Python SDK against a real server: sync and asyncio sessions, style changes, errors."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from clients.sdk import AsyncClient, Client, ServerError
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server


@pytest.fixture(scope="module")
def base():
    with live_server(load_models(get_settings().weights_dir)) as (url, _):
        yield url


def test_sync_session_streams_and_switches_style(base, bn_walk):
    client = Client(base)
    assert {m.name for m in client.models()} >= {"lti", "erd"}
    root, rot = bn_walk.translations[:20, 1], bn_walk.rotations[:20]
    with client.session(model="lti", style="elderly") as session:
        frames = [session.stylise(root[t], rot[t]) for t in range(10)]
        ack = session.set_style("exhausted", transition_frames=5)
        assert ack["type"] == "style_set"
        frames += [session.stylise(root[t], rot[t]) for t in range(10, 20)]
    assert [f.seq for f in frames] == list(range(20))
    assert all(f.rotations.shape == (22, 4) and np.isfinite(f.root).all() for f in frames)


def test_async_session_gives_the_same_frames_as_sync(base, bn_walk):
    root, rot = bn_walk.translations[:8, 1], bn_walk.rotations[:8]
    with Client(base).session(model="erd", style="elderly") as session:
        sync = [session.stylise(root[t], rot[t]).rotations for t in range(8)]

    async def run():
        async with AsyncClient(base).session(model="erd", style="elderly") as session:
            return [(await session.stylise(root[t], rot[t])).rotations for t in range(8)]

    np.testing.assert_allclose(np.array(asyncio.run(run())), np.array(sync), atol=1e-6)


def test_server_errors_become_typed_exceptions(base):
    with pytest.raises(ServerError) as err:
        Client(base).session(model="lti", style="no-such-style")
    assert err.value.code == "unknown_style"


def test_session_resumes_by_itself_after_the_connection_drops(base, bn_walk):
    """The socket dies mid-stream; the next stylise() reconnects with the resume token and the
    outputs equal an uninterrupted run."""
    root, rot = bn_walk.translations[:30, 1], bn_walk.rotations[:30]
    with Client(base).session(model="lti", style="elderly") as session:
        whole = [session.stylise(root[t], rot[t]).rotations for t in range(30)]
    with Client(base).session(model="lti", style="elderly") as session:
        first = [session.stylise(root[t], rot[t]).rotations for t in range(15)]
        token = session.resume_token
        session.ws.close()  # the connection drops
        rest = [session.stylise(root[t], rot[t]).rotations for t in range(15, 30)]
        assert session.resume_token == token and session.info["last_seq"] == 14
    np.testing.assert_allclose(np.array(first + rest), np.array(whole), atol=1e-6)
