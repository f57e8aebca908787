"""The streaming service end to end: a real server on loopback, real WebSocket clients, the
committed models, real Bandai Namco frames."""

from __future__ import annotations

import json
import struct
import threading
import time

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from models.interface import FrameBatch, style_vector
from models.registry import load_models
from models.settings import get_settings
from service import protocol as P

from .live_server import live_server, offline, ws_url
from .waiting import wait_until

N_FRAMES = 60


@pytest.fixture(scope="module")
def models():
    loaded = load_models(get_settings().weights_dir)
    assert "lti" in loaded, "the committed LTI weights must load"
    return loaded


@pytest.fixture(scope="module")
def server(models):
    with live_server(models, idle_timeout_s=30) as (base, app):
        yield base, app


@pytest.fixture(scope="module")
def clip(bn_walk):
    m = bn_walk.slice(0, N_FRAMES)
    return m.translations[:, 1].copy(), m.rotations.copy()  # Hips translation, local rotations


def start(ws, **fields) -> dict:
    ws.send(json.dumps({"type": "start", "model": "lti", **fields}))
    return json.loads(ws.recv(timeout=10))


def stream_json(ws, root, rot, seq0: int = 0) -> tuple[np.ndarray, np.ndarray]:
    roots, rots = [], []
    for t in range(len(root)):
        ws.send(json.dumps({"type": "frame", "seq": seq0 + t, "root": root[t].tolist(), "rotations": rot[t].tolist()}))
        reply = json.loads(ws.recv(timeout=10))
        assert reply["type"] == "frame" and reply["seq"] == seq0 + t and reply["dropped"] == 0, reply
        roots.append(reply["root"])
        rots.append(reply["rotations"])
    return np.array(roots), np.array(rots)


def first_style(models) -> str:
    return models["lti"].styles()[0]


def test_streamed_walk_equals_offline_model_output(server, models, clip):
    base, _ = server
    style = first_style(models)
    with connect(ws_url(base)) as ws:
        started = start(ws, style=style)
        assert started["type"] == "started" and started["joints"] == list(models["lti"].skeleton.names)
        got_root, got_rot = stream_json(ws, *clip)
    want_root, want_rot = offline(models["lti"], {style: 1.0}, *clip)
    np.testing.assert_allclose(got_root, want_root, atol=1e-9)
    np.testing.assert_allclose(got_rot, want_rot, atol=1e-9)
    assert not np.allclose(
        got_rot, clip[1] / np.linalg.norm(clip[1], axis=-1, keepdims=True), atol=1e-3
    )  # it did something


def test_binary_and_json_give_the_same_numbers(server, models, clip):
    base, _ = server
    style = first_style(models)
    root, rot = clip
    root32, rot32 = root.astype(np.float32).astype(np.float64), rot.astype(np.float32).astype(np.float64)
    with connect(ws_url(base)) as ws:
        start(ws, style=style, encoding="binary")
        got = []
        for t in range(len(root)):
            ws.send(P.encode_binary(t, root[t], rot[t]))
            data = ws.recv(timeout=10)
            assert isinstance(data, bytes) and len(data) == P.binary_frame_size(22)
            seq, kind, dropped = struct.unpack_from("<IHH", data)
            assert (seq, kind, dropped) == (t, 1, 0)
            got.append(np.frombuffer(data, "<f4", offset=8))
    with connect(ws_url(base)) as ws:
        start(ws, style=style)
        j_root, j_rot = stream_json(ws, root32, rot32)
    got = np.array(got)
    np.testing.assert_allclose(got[:, :3], j_root, atol=1e-3)  # float32 on the wire
    np.testing.assert_allclose(got[:, 3:].reshape(-1, 22, 4), j_rot, atol=1e-5)


def test_concurrent_sessions_with_different_styles_do_not_mix(server, models, clip):
    base, _ = server
    styles = models["lti"].styles()[:2]
    results: dict[str, tuple] = {}

    def run(style: str) -> None:
        with connect(ws_url(base)) as ws:
            start(ws, style=style)
            results[style] = stream_json(ws, *clip)

    threads = [threading.Thread(target=run, args=(s,)) for s in styles]
    [t.start() for t in threads]
    [t.join() for t in threads]
    for style in styles:
        want_root, want_rot = offline(models["lti"], {style: 1.0}, *clip)
        np.testing.assert_allclose(results[style][0], want_root, atol=1e-9)
        np.testing.assert_allclose(results[style][1], want_rot, atol=1e-9)
    assert not np.allclose(results[styles[0]][1], results[styles[1]][1], atol=1e-4)


def test_batching_changes_nothing_but_speed(server, models, clip):
    """Eight sessions at once share batched steps; each equals its solo run."""
    base, app = server
    style = first_style(models)
    want_root, want_rot = offline(models["lti"], {style: 1.0}, *clip)
    outputs = [None] * 8

    def run(i: int) -> None:
        with connect(ws_url(base)) as ws:
            start(ws, style=style)
            outputs[i] = stream_json(ws, *clip)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(8)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    for got_root, got_rot in outputs:
        np.testing.assert_allclose(got_root, want_root, atol=1e-9)
        np.testing.assert_allclose(got_rot, want_rot, atol=1e-9)
    metrics = httpx.get(f"{base}/metrics").text
    sizes = [
        float(l.split()[-1]) for l in metrics.splitlines() if l.startswith('stylestream_batch_size_sum{model="lti"}')
    ]
    counts = [
        float(l.split()[-1]) for l in metrics.splitlines() if l.startswith('stylestream_batch_size_count{model="lti"}')
    ]
    assert sizes[0] / counts[0] > 1.0  # some steps really did batch several sessions


def test_style_switch_mid_stream_is_continuous(server, models, clip):
    base, _ = server
    a, b = models["lti"].styles()[:2]
    root, rot = clip
    with connect(ws_url(base)) as ws:
        start(ws, style=a)
        first = stream_json(ws, root[:30], rot[:30])
        ws.send(json.dumps({"type": "style", "style": b, "transition_frames": 15}))
        ack = json.loads(ws.recv(timeout=10))
        assert ack["type"] == "style_set" and ack["weights"][b] == 1.0
        second = stream_json(ws, root[30:], rot[30:], seq0=30)
    out = np.concatenate([first[1], second[1]])
    step = np.abs(np.diff(out, axis=0)).max(axis=(1, 2))
    assert step[29:45].max() < 3 * np.percentile(step[:29], 95) + 0.02  # no jump at the switch


@pytest.mark.parametrize(
    "message, code",
    [
        ("{not json", "bad_json"),
        ('{"type": "frame", "seq": 1, "root": [0, 0, 0], "rotations": [[0, 0, 0, 1]]}', "bad_frame"),
        (
            '{"type": "frame", "seq": 1, "root": [0, 0, NaN], "rotations": ' + json.dumps([[0, 0, 0, 1]] * 22) + "}",
            "bad_frame",
        ),
        (
            '{"type": "frame", "seq": 1, "root": [0, 0, 0], "rotations": ' + json.dumps([[0, 0, 0, 0]] * 22) + "}",
            "bad_frame",
        ),
        ('{"type": "dance"}', "bad_message"),
        ('{"type": "style", "style": "no-such-style"}', "unknown_style"),
        (b"\x00\x01garbage", "bad_frame"),
        (struct.pack("<IHH", 3, 1, 0) + b"\x00" * 12, "bad_frame"),
        ("x" * (300 * 1024), "message_too_large"),
    ],
)
def test_bad_input_gets_a_typed_error_and_the_session_lives_on(server, models, clip, message, code):
    base, _ = server
    style = first_style(models)
    with connect(ws_url(base), max_size=2**24) as ws:
        start(ws, style=style)
        stream_json(ws, clip[0][:5], clip[1][:5])
        ws.send(message)
        error = json.loads(ws.recv(timeout=10))
        assert error["type"] == "error" and error["code"] == code, error
        rest = stream_json(ws, clip[0][5:10], clip[1][5:10], seq0=5)  # still alive, state intact
    want_root, want_rot = offline(models["lti"], {style: 1.0}, clip[0][:10], clip[1][:10])
    np.testing.assert_allclose(rest[1], want_rot[5:10], atol=1e-9)


@pytest.mark.parametrize(
    "first, code",
    [
        ('{"type": "frame", "seq": 0, "root": [0, 0, 0], "rotations": []}', "expected_start"),
        ('{"type": "start", "model": "nope", "style": "x"}', "unknown_model"),
        ('{"type": "start", "model": "lti", "style": "no-such-style"}', "unknown_style"),
        ('{"type": "start", "model": "lti", "style": "a", "mix": {"a": 1}}', "bad_style"),
        ('{"type": "start", "model": "lti", "style": "x", "resume_token": "forged"}', "unknown_resume_token"),
        (
            '{"type": "start", "model": "lti", "style": "elderly", "bvh_header": "HIERARCHY\\nROOT Hips\\n{"}',
            "bad_skeleton",
        ),
    ],
)
def test_bad_session_openings_are_refused_with_a_typed_error(server, first, code):
    base, _ = server
    with connect(ws_url(base)) as ws:
        ws.send(first)
        error = json.loads(ws.recv(timeout=10))
        assert error["type"] == "error" and error["code"] == code, error
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=10)
        assert closed.value.rcvd.code == 1008


def test_a_bad_client_does_not_disturb_a_good_one(server, models, clip):
    base, _ = server
    style = first_style(models)
    good: list = []

    def well_behaved() -> None:
        with connect(ws_url(base)) as ws:
            start(ws, style=style)
            good.append(stream_json(ws, *clip))

    thread = threading.Thread(target=well_behaved)
    thread.start()
    with connect(ws_url(base)) as bad:
        start(bad, style=style)
        for i in range(200):
            bad.send(["{", b"\x07" * 9, '{"type":"frame","seq":1,"root":[1,2],"rotations":[]}'][i % 3])
        codes = {json.loads(bad.recv(timeout=10))["code"] for _ in range(200)}
        assert codes == {"bad_json", "bad_frame", "bad_message"}
    thread.join()
    want_root, want_rot = offline(models["lti"], {style: 1.0}, *clip)
    np.testing.assert_allclose(good[0][1], want_rot, atol=1e-9)


class SlowModel:
    """A model that takes 20 ms a step, so a client sending 60 frames at once is sure to outrun it
    (the real compiled steps are fast enough that whether the queue overflows is up to the scheduler)."""

    def __init__(self, model, step_s: float = 0.02) -> None:
        self._model, self._step_s = model, step_s

    def __getattr__(self, name):
        if name.startswith("_"):  # copies and pickles probe before __init__ ran
            raise AttributeError(name)
        return getattr(self._model, name)

    def step_batch(self, *args, **kwargs):
        time.sleep(self._step_s)
        return self._model.step_batch(*args, **kwargs)


def test_backpressure_drops_oldest_frames_and_says_so(models, clip):
    root, rot = clip
    with live_server({"lti": SlowModel(models["lti"])}, session_queue=4, batch_wait_ms=5) as (base, _):
        with connect(ws_url(base)) as ws:
            start(ws, style=first_style(models))
            sent = 60
            payload = [
                json.dumps({"type": "frame", "seq": t, "root": root[t].tolist(), "rotations": rot[t].tolist()})
                for t in range(sent)
            ]
            for p in payload:
                ws.send(p)
            ws.send(json.dumps({"type": "end"}))
            replies, dropped = [], 0
            while True:
                msg = json.loads(ws.recv(timeout=10))
                if msg["type"] == "ended":
                    break
                replies.append(msg["seq"])
                dropped += msg["dropped"]
    assert replies == sorted(replies) and replies[-1] == sent - 1  # in order, the newest made it
    assert len(replies) + dropped == sent and dropped > 0


def test_resume_after_a_dropped_connection_continues_exactly(server, models, clip):
    base, _ = server
    style = first_style(models)
    root, rot = clip
    with connect(ws_url(base)) as ws:
        token = start(ws, style=style)["resume_token"]
        first = stream_json(ws, root[:25], rot[:25])
    with connect(ws_url(base)) as ws:
        started = start(ws, style=style, resume_token=token)
        assert started["last_seq"] == 24
        second = stream_json(ws, root[25:], rot[25:], seq0=25)
    want_root, want_rot = offline(models["lti"], {style: 1.0}, root, rot)
    np.testing.assert_allclose(np.concatenate([first[1], second[1]]), want_rot, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([first[0], second[0]]), want_root, atol=1e-9)


def test_faster_clients_get_every_frame_while_the_model_keeps_its_rate(server, models, clip, bn_walk):
    """A 120 fps stream (the 30 fps clip interpolated up, so the model's own times fall on
    frames): one reply per frame, the model stepping on every 4th frame on those very frames, and
    each reply the model's output 3 frames (the stated 25 ms) earlier: exactly a model output on
    every 4th frame, a new pose in between (no held ones)."""
    from models.motion.resample import resample

    base, _ = server
    style = first_style(models)
    fast = resample(bn_walk.slice(0, N_FRAMES), 120.0)
    fast_root, fast_rot = fast.translations[:, 1], fast.rotations
    fast_root[::4], fast_rot[::4] = clip  # the very frames (resampling may flip a quaternion's sign)
    with connect(ws_url(base)) as ws:
        started = start(ws, style=style, fps=120)
        assert started["output_delay_ms"] == pytest.approx(25.0)
        got_root, got_rot = stream_json(ws, fast_root, fast_rot)
    want_root, want_rot = offline(models["lti"], {style: 1.0}, *clip)
    assert len(got_root) == len(fast_root)
    n = len(want_rot[:-1])
    np.testing.assert_allclose(got_rot[3::4][:n], want_rot[:n], atol=1e-9)
    np.testing.assert_allclose(got_root[3::4][:n], want_root[:n], atol=1e-9)
    assert (np.abs(np.diff(got_rot[3:], axis=0)).max(axis=(1, 2)) > 1e-6).all()  # a new pose every frame


def test_metrics_show_the_latency_histogram(server):
    base, _ = server
    text = httpx.get(f"{base}/metrics").text
    assert 'stylestream_frame_latency_seconds_bucket{le="0.001",model="lti"}' in text
    assert "stylestream_active_sessions" in text and "stylestream_errors_total" in text


def test_tokens_guard_rest_and_websocket(models):
    with live_server(models, api_tokens=["s3cret"]) as (base, _):
        assert httpx.get(f"{base}/v1/models").status_code == 401
        assert httpx.get(f"{base}/v1/models", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert httpx.get(f"{base}/v1/models?token=s3cret").status_code == 200
        assert httpx.get(f"{base}/healthz").status_code == 200  # probes stay open
        with connect(ws_url(base)) as ws:
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)
            assert closed.value.rcvd.code == 4401
        with connect(ws_url(base, "/v1/stream?token=s3cret")) as ws:
            assert start(ws, style=first_style(models))["type"] == "started"
    with live_server(models) as (base, _):
        assert httpx.get(f"{base}/v1/models").status_code == 200


def test_snapshots_survive_a_round_trip_through_json(server, models, clip):
    """The portable snapshot form (for a shared store) restores the exact session."""
    from service.sessions import Session, Snapshot

    model = models["lti"]
    style = first_style(models)
    session = Session(
        model=model, skeleton="bandai-namco", fps=30.0, encoding="json", weights={style: 1.0}, state=model.init_state(1)
    )
    root, rot = clip
    state = session.state
    w = style_vector(model, {style: 1.0})[None]
    for t in range(10):
        _, state = model.step_batch(state, FrameBatch(root[t : t + 1], rot[t : t + 1]), w)
    session.state, session.last_seq = state, 9
    again = Session.restore(Snapshot.from_json(session.snapshot().to_json()), model, queue_size=8)
    assert again.last_seq == 9 and again.weights == {style: 1.0}
    for key, value in state.items():
        np.testing.assert_array_equal(again.state[key], value)


def test_idle_sessions_are_closed_and_freed(models, clip):
    with live_server(models, idle_timeout_s=0.5) as (base, app):
        with connect(ws_url(base)) as ws:
            start(ws, style=first_style(models))
            stream_json(ws, clip[0][:3], clip[1][:3])
            error = json.loads(ws.recv(timeout=10))  # then silence
            assert error["code"] == "idle_timeout"
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)
            assert closed.value.rcvd.code == 4408
        # the server frees the session after the close reaches the client: wait for it, do not race it
        wait_until(lambda: app.state.runtime.sessions == {}, "the idle session to be freed")
