"""Crowds (protocol v1.1): many characters on one connection, each exactly as if streamed alone.

A real server on loopback, the committed models, real Bandai Namco walks; the crowd driven
through the SDK (`Client.crowd`), each character compared bit for bit with the same character
streamed alone in a session of its own (`Client.session`)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from websockets.sync.client import connect

from clients.sdk import AsyncClient, Character, Client
from models.data import build_index, load_motion, select
from models.registry import load_models
from models.settings import get_settings
from service import protocol as P

from .live_server import live_server, ws_url
from .waiting import wait_until

TICKS, FPS = 24, 60.0  # 60 fps in, the models' 30 out: rate adaptation runs per character


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


@pytest.fixture(scope="module")
def server(models):
    with live_server(models, idle_timeout_s=30, max_characters=40, token_max_characters=40) as (base, _app):
        yield base


@pytest.fixture(scope="module")
def walks():
    clips = select(build_index(), dataset="bandai-namco-2", style="normal", split="val")[:5]
    return [load_motion(c).slice(0, TICKS) for c in clips]


def alone(base: str, model: str, style: str, motion, start: int = 0, restyle: tuple | None = None):
    """One character in a session of its own from tick `start`: (roots, rotations) per tick."""
    roots, rots = [], []
    with Client(base, timeout=30) as client, client.session(model=model, style=style, fps=FPS) as s:
        for t in range(start, TICKS):
            if restyle is not None and t == restyle[0]:
                s.set_style(restyle[1], transition_frames=restyle[2])
            out = s.stylise(motion.translations[t, 1], motion.rotations[t])
            roots.append(out.root)
            rots.append(out.rotations)
    return np.array(roots), np.array(rots)


@pytest.mark.parametrize("model", ["lti", "erd", "lpn"])
def test_each_character_of_a_crowd_gets_what_it_gets_alone(server, models, walks, model):
    """Five characters with their own styles, one sending its joints in another order, one
    joining mid-stream, one changing style with a transition: every reply equals that
    character's own session's, bit for bit."""
    styles = models[model].styles()
    names = list(models[model].skeleton.names)
    order = np.roll(np.arange(len(names)), 5)  # character 3 sends its joints in this order
    crowd_roots: dict[int, list] = {i: [] for i in range(5)}
    crowd_rots: dict[int, list] = {i: [] for i in range(5)}
    chars = [Character(i, model, styles[i % len(styles)]) for i in range(4)]
    chars[3] = Character(3, model, styles[3 % len(styles)], joints=[names[k] for k in order])
    with Client(server, timeout=30) as client, client.crowd(chars, fps=FPS) as crowd:
        assert crowd.errors == [] and sorted(crowd.characters) == [0, 1, 2, 3]
        for t in range(TICKS):
            if t == 6:
                crowd.join([Character(4, model, styles[-1])])
            if t == 9:
                crowd.set_style(styles[0], characters=[1], transition_frames=8)
            ids = [0, 1, 2, 3, 4] if t >= 6 else [0, 1, 2, 3]
            rots = [walks[i].rotations[t] if i != 3 else walks[i].rotations[t][order] for i in ids]
            out = crowd.tick(ids, np.stack([walks[i].translations[t, 1] for i in ids]), np.stack(rots))
            assert out.seq == t and list(out.ids) == ids and out.dropped == 0
            for i in ids:
                root, rot = out.frame(i)
                crowd_roots[i].append(root.copy())
                back = np.empty_like(rot)
                back[order] = rot
                crowd_rots[i].append(back if i == 3 else rot.copy())
        assert crowd.errors == []
    for i in range(5):
        restyle = (9, styles[0], 8) if i == 1 else None
        want_root, want_rot = alone(
            server, model, chars[i].style if i < 4 else styles[-1], walks[i], 6 * (i == 4), restyle
        )
        assert np.array_equal(np.array(crowd_roots[i]), want_root.astype(np.float32)), i
        assert np.array_equal(np.array(crowd_rots[i]), want_rot.astype(np.float32)), i


def test_a_refused_frame_or_character_costs_only_its_own(server, models, walks):
    lti = models["lti"].styles()
    chars = [
        Character(7, "lti", lti[0]),
        Character(8, "lti", "no-such-style"),
        Character(9, "nope", lti[0]),
        Character(10, "lti", lti[1]),
    ]
    with Client(server, timeout=30) as client, client.crowd(chars, fps=30) as crowd:
        assert sorted(crowd.characters) == [7, 10]
        assert {(e.character, e.code) for e in crowd.errors} == {(8, "unknown_style"), (9, "unknown_model")}
        roots = np.stack([walks[0].translations[0, 1], walks[1].translations[0, 1]])
        rots = np.stack([walks[0].rotations[0], walks[1].rotations[0]])
        rots[0, 4, :] = np.nan
        out = crowd.tick([7, 10], roots, rots)
        assert list(out.ids) == [10]  # 7's frame refused, 10's stylised
        assert (crowd.errors[-1].character, crowd.errors[-1].code) == (7, "bad_frame")
        with pytest.raises(Exception) as refused:  # a character not in the crowd: the tick is refused
            crowd.tick([7, 99], roots, rots)
        assert getattr(refused.value, "code", None) == "unknown_character"
        assert crowd.leave([10, 55]) == [10]
        out = crowd.tick([7], roots[:1], np.stack([walks[0].rotations[0]]))
        assert list(out.ids) == [7]


def test_the_server_caps_characters_and_a_full_crowd_still_streams(server, models, walks):
    style = models["lti"].styles()[0]
    motion = walks[2]
    with (
        Client(server, timeout=30) as client,
        client.crowd([Character(i, "lti", style) for i in range(30)], FPS) as crowd,
    ):
        joined = crowd.join([Character(100 + i, "lti", style) for i in range(20)])  # 30 + 20 > 40: none joins
        assert joined["characters"] == [] and {e["code"] for e in joined["errors"]} == {"too_many_characters"}
        got = []
        for t in range(TICKS):
            out = crowd.tick(
                range(30), np.tile(motion.translations[t, 1], (30, 1)), np.tile(motion.rotations[t], (30, 1, 1))
            )
            got.append(out.arrays()[1].copy())
    _, want_rot = alone(server, "lti", style, motion)
    for k in (0, 17, 29):  # thirty copies of one walk: thirty copies of its reply
        assert np.array_equal(np.array(got)[:, k], want_rot.astype(np.float32))


def test_a_crowd_opens_with_the_asyncio_client_and_speaks_binary_ticks_only(server, models, walks):
    style = models["erd"].styles()[0]

    async def run():
        async with AsyncClient(server, timeout=30) as client:
            crowd = await client.crowd([Character(1, "erd", style), Character(2, "erd", style)], fps=30)
            out = await crowd.tick([1, 2], walks[0].translations[:2, 1], walks[0].rotations[:2])
            await crowd.close()
            return out

    roots, rots = asyncio.run(run()).arrays()
    assert rots.shape == (2, 22, 4) and np.allclose(np.linalg.norm(rots, axis=-1), 1.0, atol=1e-5)
    with connect(ws_url(server)) as ws:  # JSON frames and ticks of the wrong kind are typed errors
        ws.send(json.dumps({"type": "crowd", "characters": [{"id": 1, "model": "lti", "style": style}]}))
        assert json.loads(ws.recv(timeout=30))["type"] == "crowd_started"
        ws.send(json.dumps({"type": "frame", "seq": 0, "root": [0, 0, 0], "rotations": []}))
        assert json.loads(ws.recv(timeout=30))["code"] == "bad_message"
        ws.send(P.encode_binary(0, np.zeros(3), np.tile([0.0, 0, 0, 1], (22, 1))))
        assert json.loads(ws.recv(timeout=30))["code"] == "bad_frame"


def test_a_crowd_resumes_every_character_exactly_where_it_left_off(models, walks):
    """Characters of two models, one mid-transition, one on reordered joints: the connection
    drops after 10 ticks, a new crowd picks them up by their resume tokens (under new ids), and
    every later reply equals an uninterrupted crowd's, bit for bit."""
    lti, erd = models["lti"].styles(), models["erd"].styles()
    names = list(models["lti"].skeleton.names)
    order = np.roll(np.arange(len(names)), 3)
    chars = [
        Character(0, "lti", lti[1]),
        Character(1, "erd", erd[2]),
        Character(2, "lti", lti[3], joints=[names[k] for k in order]),
    ]

    def frames(t: int):
        rots = [walks[i].rotations[t] if i != 2 else walks[i].rotations[t][order] for i in range(3)]
        return np.stack([walks[i].translations[t, 1] for i in range(3)]), np.stack(rots)

    def run(crowd, ids, ticks) -> list[np.ndarray]:
        out = []
        for t in ticks:
            if t == 7:
                crowd.set_style(lti[0], characters=[ids[0]], transition_frames=8)
            reply = crowd.tick(ids, *frames(t))
            out.append(np.concatenate([reply.frame(i)[1].ravel() for i in ids]))
        return out

    with live_server(models, idle_timeout_s=30) as (base, app), Client(base, timeout=30) as client:
        with client.crowd(chars, fps=FPS) as crowd:
            want = run(crowd, [0, 1, 2], range(TICKS))
        crowd = client.crowd(chars, fps=FPS)
        run(crowd, [0, 1, 2], range(10))
        tokens = crowd.resume_tokens
        crowd.io.ws.close()  # the connection drops (no 'end'): each character stays resumable
        runtime = app.state.runtime
        wait_until(lambda: not runtime.crowd_members, "the dropped crowd's characters were not stored")
        again = [Character.resuming(10 + i, chars[i].model, tokens[i]) for i in range(3)]
        again.append(Character.resuming(13, "lti", "no-such-token"))
        with client.crowd(again, fps=FPS) as resumed:
            assert resumed.resumed == {10: 9, 11: 9, 12: 9}
            assert [(e.character, e.code) for e in resumed.errors] == [(13, "unknown_resume_token")]
            got = run(resumed, [10, 11, 12], range(10, TICKS))
        for t, (a, b) in enumerate(zip(got, want[10:], strict=True)):
            assert np.array_equal(a, b), t
        # the tokens were taken up: a second resume of the same characters is refused
        with client.crowd([Character.resuming(20, "lti", tokens[0])], fps=FPS) as late:
            assert [e.code for e in late.errors] == ["unknown_resume_token"]


def test_a_callers_crowds_share_its_own_character_cap(models, walks):
    """`token_max_characters`: one caller (here a client address) cannot take every character
    the server holds; across its connections, a join that does not fit is refused whole."""
    style = models["lti"].styles()[0]
    with live_server(models, token_max_characters=6) as (base, _), Client(base, timeout=30) as client:
        with client.crowd([Character(i, "lti", style) for i in range(4)], fps=FPS) as a:
            joined = a.join([Character(10 + i, "lti", style) for i in range(3)])
            assert joined["characters"] == [] and {e["code"] for e in joined["errors"]} == {"too_many_characters"}
            assert "this client address holds its maximum of 6" in joined["errors"][0]["message"]
            with client.crowd([Character(i, "lti", style) for i in range(2)], fps=FPS) as b:  # 4 + 2 = 6
                assert b.errors == [] and b.characters == [0, 1]
                refused = b.join([Character(5, "lti", style)])
                assert refused["characters"] == [] and refused["errors"][0]["code"] == "too_many_characters"
                a.leave([0])
                assert b.join([Character(5, "lti", style)])["characters"][0]["id"] == 5
                out = b.tick(
                    [0, 1, 5], np.tile(walks[0].translations[0, 1], (3, 1)), np.tile(walks[0].rotations[0], (3, 1, 1))
                )
                assert list(out.ids) == [0, 1, 5]


def test_a_crowd_comes_back_by_itself_when_its_connection_drops(models, walks):
    """The socket dies after tick 11 (a style transition under way): the next `tick` reconnects,
    resumes every character by its token and answers as the uninterrupted crowd does."""
    lti, erd = models["lti"].styles(), models["erd"].styles()
    chars = [Character(0, "lti", lti[2]), Character(1, "erd", erd[1])]

    def run(crowd, on_tick=None) -> list[np.ndarray]:
        out = []
        for t in range(TICKS):
            if t == 5:
                crowd.set_style(lti[4], characters=[0], transition_frames=10)
            reply = crowd.tick(
                [0, 1],
                np.stack([w.translations[t, 1] for w in walks[:2]]),
                np.stack([w.rotations[t] for w in walks[:2]]),
            )
            out.append(np.concatenate([reply.frame(i)[1].ravel() for i in (0, 1)]))
            if on_tick:
                on_tick(crowd, t)
        return out

    def drop(crowd, t: int) -> None:
        if t == 11:
            crowd.io.ws.close()

    with live_server(models, idle_timeout_s=30) as (base, _), Client(base, timeout=30) as client:
        with client.crowd(chars, fps=FPS) as crowd:
            want = run(crowd)
        with client.crowd(chars, fps=FPS, reconnect_timeout=10) as crowd:
            got = run(crowd, drop)
            assert crowd.reconnects == 1
            event = crowd.last_reconnect
            assert (event.last_seq, event.replayed, event.fresh) == (11, 1, [])
    for t, (g, w) in enumerate(zip(got, want, strict=True)):
        assert np.array_equal(g, w), t


def test_characters_the_store_forgot_start_over_after_a_drop(models, walks):
    """The connection drops and the server no longer knows the characters' tokens: the reconnect
    rejoins them fresh, and the next tick answers for both (each with its own rig's frame)."""
    lti = models["lti"].styles()
    chars = [Character(0, "lti", lti[2]), Character(1, "erd", models["erd"].styles()[1])]
    with live_server(models, idle_timeout_s=30) as (base, _), Client(base, timeout=30) as client:
        with client.crowd(chars, fps=FPS, reconnect_timeout=10) as crowd:
            for t in range(4):
                crowd.tick(
                    [0, 1],
                    np.stack([w.translations[t, 1] for w in walks[:2]]),
                    np.stack([w.rotations[t] for w in walks[:2]]),
                )
            for i in (0, 1):
                crowd.core.resume_tokens[i] = f"forgotten-{i}-" + "x" * 20  # as if they had expired
            crowd.io.ws.close()
            reply = crowd.tick(
                [0, 1],
                np.stack([w.translations[4, 1] for w in walks[:2]]),
                np.stack([w.rotations[4] for w in walks[:2]]),
            )
            assert crowd.reconnects == 1 and crowd.last_reconnect.fresh == [0, 1]
            assert all(np.isfinite(reply.frame(i)[1]).all() for i in (0, 1))


def test_controller_ticks_drive_each_lpn_character_as_its_own_session(server, models):
    """Controller ticks (kind 3): LPN-FiLM characters in a crowd synthesise from the desired
    motion exactly as a session does from `control` messages; a character of a model that is no
    controller, or with a NaN in its values, is refused alone."""
    lpn, lti = models["lpn"].styles(), models["lti"].styles()
    plan = [((1.1 + 0.03 * t, 0.2 - 0.02 * t), 0.05 * t, "run" if t >= 16 else "walk") for t in range(TICKS)]
    chars = [Character(0, "lpn", lpn[0]), Character(1, "lpn", lpn[4]), Character(2, "lti", lti[0])]
    got: dict[int, list] = {0: [], 1: []}
    with Client(server, timeout=30) as client:
        with client.crowd(chars, fps=FPS) as crowd:
            for velocity, facing, gait in plan:
                out = crowd.control([0, 1, 2], np.tile(velocity, (3, 1)), np.full(3, facing), gait)
                assert list(out.ids) == [0, 1]
                for i in (0, 1):
                    got[i].append(np.concatenate([out.frame(i)[0], out.frame(i)[1].ravel()]))
            assert {e.code for e in crowd.errors} == {"control_unsupported"} and len(crowd.errors) == TICKS
            assert {e.character for e in crowd.errors} == {2}
            bad = crowd.control([0, 1], np.array([[1.0, 0.0], [np.nan, 0.0]]), np.zeros(2))
            assert list(bad.ids) == [0] and (crowd.errors[-1].character, crowd.errors[-1].code) == (1, "bad_frame")
        for i, style in ((0, lpn[0]), (1, lpn[4])):
            with client.session(model="lpn", style=style, fps=FPS) as alone:
                want = [alone.control(v, f, g) for v, f, g in plan]
            want_rows = np.array([np.concatenate([w.root, w.rotations.ravel()]) for w in want], np.float32)
            assert np.array_equal(np.array(got[i]), want_rows), i


def test_a_crowd_character_resumes_as_a_session_and_a_session_as_a_crowd_character(models, walks):
    """One snapshot format for both: a crowd character's token opens a session that goes on
    exactly where the character was, and a session's token a crowd character."""
    style = models["lti"].styles()[1]
    walk = walks[0]
    floats = 3 + 4 * walk.rotations.shape[1]

    def crowd_run(crowd, span):
        return [
            crowd.tick([0], walk.translations[t, 1][None], walk.rotations[t][None]).frame(0)[1].copy() for t in span
        ]

    with live_server(models, idle_timeout_s=30) as (base, app), Client(base, timeout=30) as client:
        runtime = app.state.runtime
        with client.crowd([Character(0, "lti", style)], fps=FPS) as whole:
            want = crowd_run(whole, range(TICKS))
        crowd = client.crowd([Character(0, "lti", style)], fps=FPS, reconnect_timeout=0)
        crowd_run(crowd, range(8))
        token = crowd.resume_tokens[0]
        crowd.io.ws.close()
        wait_until(lambda: not runtime.crowd_members, "the crowd character was not stored")
        with connect(ws_url(base)) as ws:  # the character as a session (its snapshot speaks binary)
            ws.send(json.dumps({"type": "start", "model": "lti", "resume_token": token}))
            started = json.loads(ws.recv(timeout=30))
            assert started["type"] == "started" and started["last_seq"] == 7 and started["encoding"] == "binary"
            for t in range(8, 12):
                payload = np.concatenate([walk.translations[t, 1], walk.rotations[t].ravel()]).astype("<f4")
                ws.send(P.BINARY_HEADER.pack(t, P.KIND_FRAME, 0) + payload.tobytes())
                reply = np.frombuffer(ws.recv(timeout=30), "<f4", offset=P.BINARY_HEADER.size)
                assert len(reply) == floats and np.array_equal(reply[3:].reshape(-1, 4), want[t]), t
        with client.session(model="lti", style=style, fps=FPS) as session:  # and a session as a character
            alone = [session.stylise(walk.translations[t, 1], walk.rotations[t]).rotations for t in range(8)]
            token = session.resume_token
            session.ws.close()  # the connection drops: the session stays resumable
            wait_until(lambda: not runtime.sessions, "the session was not stored")
            with client.crowd([Character.resuming(5, "lti", token)], fps=FPS) as resumed:
                assert resumed.resumed == {5: 7}
                got = [
                    resumed.tick([5], walk.translations[t, 1][None], walk.rotations[t][None]).frame(5)[1].copy()
                    for t in range(8, 12)
                ]
        assert np.array_equal(np.array(alone, np.float32), np.array(want[:8]))
        assert np.array_equal(np.array(got), np.array(want[8:12]))


def test_a_connected_characters_token_is_in_use_not_unknown(models):
    """A reconnect can reach the server before it notices the old connection is gone, when nothing
    of the character is stored yet: its token is still in use (the client tries again), not
    unknown (the client would start the character over)."""
    with live_server(models, idle_timeout_s=30) as (base, _):
        with connect(ws_url(base)) as first, connect(ws_url(base)) as second:
            first.send(json.dumps({"type": "crowd", "characters": [{"id": 0, "model": "lti", "style": "elderly"}]}))
            token = json.loads(first.recv(timeout=30))["characters"][0]["resume_token"]
            second.send(
                json.dumps(
                    {
                        "type": "crowd",
                        "characters": [{"id": 0, "model": "lti", "style": "elderly", "resume_token": token}],
                    }
                )
            )
            reply = json.loads(second.recv(timeout=30))
            assert [e["code"] for e in reply["errors"]] == ["session_in_use"]


def test_a_crowd_is_not_a_batchmate_that_sessions_frames_wait_for(models):
    """A session's frame waits (`batch_wait_ms`) only for other sessions' frames to batch with:
    a crowd, idle or ticking, never makes it wait for a part that is not coming
    (`service.batcher`). The batcher's count of requests to wait for stays the sessions' while
    a crowd of the same model opens, joins and leaves."""
    with live_server(models, idle_timeout_s=30) as (base, app):
        batcher = app.state.runtime.batchers["lti"]
        with Client(base, timeout=30) as client, client.session(model="lti", style="elderly", fps=FPS):
            assert batcher.open_sessions() == 1
            with connect(ws_url(base)) as ws:
                ws.send(json.dumps({"type": "crowd", "characters": [{"id": 0, "model": "lti", "style": "elderly"}]}))
                assert json.loads(ws.recv(timeout=30))["characters"][0]["id"] == 0
                ws.send(json.dumps({"type": "join", "characters": [{"id": 1, "model": "lti", "style": "elderly"}]}))
                assert json.loads(ws.recv(timeout=30))["type"] == "joined"
                assert batcher.open_sessions() == 1
                ws.send(json.dumps({"type": "leave", "characters": [0, 1]}))
                assert json.loads(ws.recv(timeout=30))["type"] == "left"
                assert batcher.open_sessions() == 1
        wait_until(lambda: batcher.open_sessions() == 0, "the session closed", timeout=30)


def test_a_client_waiting_for_a_slow_join_is_not_idle(models):
    """A join whose rigs take longer to build than the idle timeout (a busy server) is answered:
    the client waits for the server then, it is not idle. Its idle time runs from the reply."""
    from models.motion.assets import ASSETS

    idle = 1.0
    header = (ASSETS / "cmu.bvh").read_text().split("MOTION")[0] + "MOTION\n"
    with live_server(models, idle_timeout_s=idle) as (base, app):
        builds = app.state.runtime.rig_builds
        build = builds._runner

        async def slow(fn, *args, **kwargs):  # noqa: ANN001, ANN202 - a build held past the idle timeout
            await asyncio.sleep(2.5 * idle)
            return await build(fn, *args, **kwargs)

        builds._runner = slow
        with connect(ws_url(base)) as ws:
            ws.send(json.dumps({"type": "crowd", "characters": [{"id": 0, "model": "lti", "style": "elderly"}]}))
            assert json.loads(ws.recv(timeout=30))["type"] == "crowd_started"
            joining = {"id": 1, "model": "lti", "style": "elderly", "bvh_header": header}
            ws.send(json.dumps({"type": "join", "characters": [joining]}))
            joined = json.loads(ws.recv(timeout=60))
            assert joined["type"] == "joined" and [c["id"] for c in joined["characters"]] == [1], joined
            assert json.loads(ws.recv(timeout=30))["code"] == "idle_timeout"  # and then, told nothing, idle
