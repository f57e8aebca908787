"""The pieces behind docs/performance.md and the frame path's compiled check: the capacity
search, the profile's attribution of samples, and that the one-pass frame check says and returns
exactly what the whole-array numpy version did."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from clients.loadtest import Result, find_max
from clients.server_profile import OTHER, summarise
from service import protocol as P


def _result(sessions: int, p99_ms: float, dropped: int = 0) -> Result:
    return Result(
        sessions=sessions,
        fps=60.0,
        seconds=1.0,
        sent=sessions * 60,
        received=sessions * 60 - dropped,
        dropped=dropped,
        late=0,
        lost=0,
        p50_ms=1.0,
        p95_ms=p99_ms,
        p99_ms=p99_ms,
        max_ms=p99_ms,
        frames_per_s=sessions * 60.0,
        client_cpu_s=0.0,
        client_processes=1,
    )


@pytest.mark.parametrize("true_capacity", [5, 37, 100, 700])
def test_capacity_search_lands_within_an_eighth_below_the_true_capacity(true_capacity):
    tried = []

    def measure(n: int) -> Result:
        tried.append(n)
        return _result(n, 5.0 if n <= true_capacity else 40.0)

    found = find_max(measure, 8)
    assert true_capacity - max(1, true_capacity // 8) <= found <= true_capacity
    assert len(tried) <= 18  # a failing count is measured twice


def test_one_stalled_run_does_not_set_the_capacity():
    stalled = []

    def measure(n: int) -> Result:
        if n == 8 and not stalled:  # the first run at 8 sessions meets a stall; its repeat does not
            stalled.append(n)
            return _result(n, 120.0, dropped=13)
        return _result(n, 5.0 if n <= 100 else 40.0)

    assert 88 <= find_max(measure, 8) <= 100


def test_dropped_frames_fail_a_run_whatever_the_latency():
    assert find_max(lambda n: _result(n, 1.0, dropped=1 if n > 20 else 0), 8) in range(18, 21)


def test_profile_samples_count_for_their_innermost_named_part_and_idle_threads_not_at_all():
    stacks = Counter(
        {
            "run (uvicorn/server.py:1);process (service/stream.py:258);send_bytes (service/stream.py:62);"
            "WebSocketsSansIOProtocol.send (uvicorn/protocols/websockets/websockets_sansio_impl.py:506)": 6,
            "run (uvicorn/server.py:1);Batcher._run (service/batcher.py:150);run_step (service/batcher.py:53);"
            "step_batch (models/lti/model.py:289)": 3,
            "run (uvicorn/server.py:1);on_binary (service/stream.py:210);decode_binary (service/protocol.py:185)": 2,
            "Runner.run (asyncio/runners.py:118)": 9,
            "Thread.run (threading.py:982);_worker (concurrent/futures/thread.py:81)": 7,  # idle: left out
            "WorkerThread.run (anyio/_backends/_asyncio.py:1113);Queue.get (queue.py:171);"
            "Condition.wait (threading.py:327)": 5,
        }
    )
    shares = summarise(stacks)
    assert shares["WebSocket send (uvicorn, socket write)"] == pytest.approx(0.3)
    assert shares["model step (batched)"] == pytest.approx(0.15)
    assert shares["frame decode + validation"] == pytest.approx(0.1)
    assert shares[OTHER] == pytest.approx(0.45)
    assert sum(shares.values()) == pytest.approx(1.0)


def _numpy_check(root: np.ndarray, rot: np.ndarray) -> str | tuple[np.ndarray, np.ndarray]:
    """The whole-array check the compiled one replaced: its error message, or its arrays."""
    root, rot = root.astype(np.float64), rot.astype(np.float64)
    if not (np.isfinite(root).all() and np.isfinite(rot).all()):
        return "frame contains NaN or Inf"
    with np.errstate(over="ignore"):
        norms = np.sqrt(np.einsum("ij,ij->i", rot, rot))
    if norms.min() < 1e-6:
        return "zero-length quaternion"
    if norms.max() == np.inf:
        return "quaternion components out of range"
    if np.abs(root).max() > 1e6:
        return "root translation out of range"
    return root, rot / norms[:, None]


def _frames():
    rng = np.random.default_rng(7)
    good = rng.normal(size=(22, 4))
    yield rng.normal(size=3) * 100, good
    for value in (np.nan, np.inf, -np.inf):
        for where in ("root", "rot"):
            root, rot = rng.normal(size=3), good.copy()
            (root if where == "root" else rot)[1 if where == "root" else (5, 2)] = value
            yield root, rot
    rot = good.copy()
    rot[3] = 0.0
    yield np.zeros(3), rot
    rot = good.copy()
    rot[4] = 1e160
    yield np.zeros(3), rot
    rot[9] = 0.0  # zero-length is reported before overflow, wherever it is
    yield np.zeros(3), rot
    yield np.array([0.0, 2e6, 0.0]), good


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_frame_check_matches_the_numpy_version(dtype):
    for root, rot in _frames():
        if dtype == np.float32 and np.abs(rot[np.isfinite(rot)]).max() > 1e30:
            continue  # not representable in a binary frame
        expected = _numpy_check(root.astype(dtype), rot.astype(dtype))
        if isinstance(expected, str):
            with pytest.raises(P.ProtocolError) as err:
                P.check_values(root.astype(dtype), rot.astype(dtype), 3)
            assert (err.value.code, err.value.message, err.value.seq) == ("bad_frame", expected, 3)
        else:
            got_root, got_rot = P.check_values(root.astype(dtype), rot.astype(dtype), 3)
            assert got_root.dtype == got_rot.dtype == np.float64
            np.testing.assert_allclose(got_root, expected[0], rtol=0, atol=0)
            np.testing.assert_allclose(got_rot, expected[1], rtol=1e-15, atol=1e-15)
