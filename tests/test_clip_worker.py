"""Decoding uploads off the event loop without costing the streams (issue #16): children that
live on between clips, file parts kept in memory, and background work below the streams (lower niceness, off one CPU)."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import sys
import tempfile
import threading

import numpy as np
import pytest

from service.api import ApiError
from service.background import BACKGROUND_NICE, in_background, placement, set_background
from service.clip_worker import ClipBudget, ClipDecoder, read_multipart

from .hostile import json_clip, longest_bvh
from .waiting import wait_until

BUDGET = ClipBudget(
    min_frames=30, max_frames=9000, min_fps=1.0, max_fps=1000.0, cpu_s=60.0, memory_mb=1024, wall_s=120.0
)


def json_body(walk, fps: float = 30.0) -> list[bytes]:
    return [json.dumps(json_clip("clip", walk, fps)).encode()]


Job = tuple[str, list[bytes], str]  # kind, body, content type


def decode_all(decoder: ClipDecoder, jobs: list[Job], skeleton, budgets: list[ClipBudget] | None = None) -> list:
    """Each upload decoded in turn for LPN-FiLM (each within its budget, if given); an `ApiError`
    is returned, not raised."""

    async def run() -> list:
        out = []
        for i, (kind, body, content_type) in enumerate(jobs):
            decoder.budget = budgets[i] if budgets else decoder.budget
            try:
                out.append(await decoder.decode(kind, body, {"model": "lpn"}, {"lpn": skeleton}, content_type))
            except ApiError as err:
                out.append(err)
        await in_background(decoder.close)
        return out

    return asyncio.run(run())


def test_one_decoding_child_takes_clip_after_clip(bn_walk):
    """Starting a process per upload was what the streams felt: a child that answered, clip
    or refusal, takes the next one."""
    decoder = ClipDecoder(BUDGET, concurrency=1)
    walk = bn_walk.slice(0, 60)
    good, slow = ("json", json_body(walk), ""), ("json", json_body(walk, fps=1e-4), "")
    answers = decode_all(decoder, [good, slow, good], walk.skeleton)
    assert [a.motion.num_frames for a in answers[::2]] == [60, 60]
    assert isinstance(answers[1], ApiError) and answers[1].code == "bad_frame_rate"
    assert decoder.started == 1


def test_a_child_that_ran_out_of_memory_is_not_reused(bn_walk):
    decoder = ClipDecoder(dataclasses.replace(BUDGET, memory_mb=8), concurrency=1)
    form = b'--x\r\nContent-Disposition: form-data; name="file"; filename="w.bvh"\r\n\r\n'
    big = ("multipart", [form, longest_bvh(bn_walk).encode(), b"\r\n--x--\r\n"], "multipart/form-data; boundary=x")
    slow = ("json", json_body(bn_walk.slice(0, 60), fps=1e-4), "")
    answers = decode_all(decoder, [big, slow], bn_walk.skeleton)
    assert [a.code for a in answers] == ["clip_too_large", "bad_frame_rate"]
    assert decoder.started == 2


def test_a_clip_over_its_cpu_budget_is_refused_and_the_next_gets_a_fresh_child(bn_walk):
    """1,800 rows take tens of ms of CPU to decode: far over 1 ms (the profiling timer is checked
    at the kernel's tick, so the clip must outlast a few)."""
    walk = bn_walk.slice(0, 60)
    decoder = ClipDecoder(BUDGET, concurrency=1)
    long = ("bvh", [longest_bvh(bn_walk, 1800).encode()], "")
    over, fresh = decode_all(
        decoder,
        [long, ("json", json_body(walk), "")],
        walk.skeleton,
        [dataclasses.replace(BUDGET, cpu_s=0.001), BUDGET],
    )
    assert isinstance(over, ApiError) and (over.status, over.code) == (422, "clip_too_slow")
    assert "of CPU" in over.message
    assert fresh.motion.num_frames == 60 and decoder.started == 2


def test_the_cpu_budget_counts_cpu_not_time_spent_waiting():
    """A child at nice 19 beside busy processes waits long for a core; only what it computes
    counts against the clip."""
    import time

    from service.clip_worker import _OverBudget, cpu_budget

    with cpu_budget(0.05):
        time.sleep(0.2)  # four times the budget, asleep: no CPU
    with pytest.raises(_OverBudget), cpu_budget(0.05):
        end = time.process_time() + 10
        while time.process_time() < end:
            pass


def test_a_child_given_no_cpu_in_time_is_killed_and_answered_busy(bn_walk):
    """The wall-clock limit: the server was too busy to decode in time, not the clip's fault. The
    child is stopped (SIGSTOP), so it truly gets no CPU, however fast or loaded the machine."""
    import multiprocessing
    import signal

    walk = bn_walk.slice(0, 60)
    decoder = ClipDecoder(BUDGET, concurrency=1)
    body = json_body(walk)

    async def run() -> list:
        before = set(multiprocessing.active_children())
        first = await decoder.decode("json", body, {"model": "lpn"}, {"lpn": walk.skeleton})
        (child,) = set(multiprocessing.active_children()) - before  # idle, kept for the next clip
        os.kill(child.pid, signal.SIGSTOP)
        decoder.budget = dataclasses.replace(BUDGET, wall_s=0.2)
        busy: object = None
        try:
            await decoder.decode("json", body, {"model": "lpn"}, {"lpn": walk.skeleton})
        except ApiError as err:
            busy = err
        decoder.budget = BUDGET
        fresh = await decoder.decode("json", body, {"model": "lpn"}, {"lpn": walk.skeleton})
        await in_background(decoder.close)
        return [first, busy, fresh, child.is_alive()]

    first, busy, fresh, stopped_alive = asyncio.run(run())
    assert first.motion.num_frames == 60
    assert isinstance(busy, ApiError) and (busy.status, busy.code) == (503, "server_busy")
    assert busy.headers == {"Retry-After": "30"}
    assert not stopped_alive  # killed, not left stopped
    assert fresh.motion.num_frames == 60 and decoder.started == 2


def test_a_large_file_part_is_parsed_in_memory_not_spilled_to_disk(monkeypatch):
    """Starlette spools file parts over 1 MB to a temporary file; every large upload then wrote
    to disk, which the streams felt."""

    def no_disk(self):
        raise AssertionError("a file part was spilled to disk")

    monkeypatch.setattr(tempfile.SpooledTemporaryFile, "rollover", no_disk)
    data = b"HIERARCHY\n" + b"0 " * 1_500_000
    body = b'--b\r\nContent-Disposition: form-data; name="file"; filename="a.bvh"\r\n\r\n' + data
    body += b'\r\n--b\r\nContent-Disposition: form-data; name="name"\r\n\r\nx\r\n--b--\r\n'
    file, fields = read_multipart(body, "multipart/form-data; boundary=b")
    assert file == data and fields["name"] == "x" and fields["fine_tune"] is False


def where(tid: int) -> tuple[int, set[int]]:
    """A thread's (or process's) niceness and CPU set."""
    return os.getpriority(os.PRIO_PROCESS, tid), os.sched_getaffinity(tid)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread niceness and CPU sets are Linux's")
def test_background_work_runs_below_the_event_loops_priority_and_off_one_cpu():
    async def run() -> tuple[tuple[int, set[int]], tuple[int, set[int]]]:
        return where(threading.get_native_id()), await in_background(lambda: where(threading.get_native_id()))

    (loop_nice, loop_cpus), background = asyncio.run(run())
    assert background == (max(loop_nice, BACKGROUND_NICE), set(placement().cpus or loop_cpus))
    if len(loop_cpus) > 1:
        assert len(background[1]) == len(loop_cpus) - 1


def test_background_work_is_kept_off_one_cpu_unless_told_otherwise(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert placement(10).cpus == {1, 2, 3}
    assert placement(10, cpus=2).cpus == {2, 3}
    assert placement(10, cpus=4).cpus is None and placement(10, cpus=9).cpus is None
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {5}, raising=False)
    assert placement(10).cpus is None  # one CPU: nothing to keep free


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread niceness and CPU sets are Linux's")
def test_a_serving_process_decodes_uploads_where_its_settings_say():
    from service.server import tune_interpreter
    from service.settings import ServiceSettings

    decoder = ClipDecoder(BUDGET, concurrency=1)
    switch_interval = sys.getswitchinterval()
    try:
        tune_interpreter(ServiceSettings(background_nice=15, background_cpus=1))
        child = decoder._take()  # a fresh child, as an upload would start it
        try:
            placed = (15, set(placement(15, 1).cpus or os.sched_getaffinity(0)))
            wait_until(lambda: where(child.process.pid) == placed, f"the child placed at {placed}")
        finally:
            decoder._reap(child, timeout=5.0)
    finally:
        set_background(placement())
        sys.setswitchinterval(switch_interval)


def test_the_decoding_children_never_load_torch():
    """The fork server preloads what a child runs; with torch it held 170 MB of private memory in
    every server from its start (measured in /proc/<pid>/smaps_rollup), and 1 s more CPU to start."""
    import subprocess

    check = "import sys, service.clip_worker; print(sorted(m for m in sys.modules if m.split('.')[0] == 'torch'))"
    out = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_a_decoded_clips_arrays_come_back_beside_its_pickle_not_in_it(bn_walk):
    """The thread that reads the child's answer holds the GIL for the length of any one C call,
    and unpickling ~6 MB of arrays in one call held the event loop that long: the answer's arrays
    travel out of band, in pieces, and come back equal."""
    from multiprocessing import Pipe

    from service.background import PIECE_BYTES
    from service.clip_worker import receive_answer, send_answer

    rotations = np.tile(bn_walk.rotations, (40, 1, 1))  # ~5 MB
    answer = ("ok", {"rotations": rotations, "name": "x"}, False)
    reader, writer = Pipe(duplex=False)
    sent: list[int] = []
    original = writer.send_bytes
    writer.send_bytes = lambda data, *a: (sent.append(len(memoryview(data))), original(data, *a))[1]
    thread = threading.Thread(target=send_answer, args=(writer, answer))
    thread.start()
    got = receive_answer(reader)
    thread.join()
    np.testing.assert_array_equal(got[1]["rotations"], rotations)
    assert got[0] == "ok" and got[1]["name"] == "x" and got[2] is False
    assert sent[0] < 10_000 and max(sent) <= PIECE_BYTES < rotations.nbytes  # the pickle, then pieces


def test_style_files_saved_in_pieces_load_back_exactly(bn_walk, tmp_path):
    """`save_npz` writes what `np.savez` would (read back by `np.load`): a clip's arrays, a
    transposed (non-contiguous) one and a scalar, each exactly."""
    from service.background import save_npz

    rotations = np.tile(bn_walk.rotations, (20, 1, 1))  # several pieces
    save_npz(tmp_path / "clip.npz", rotations=rotations, root=bn_walk.translations[:, 0].T, fps=30.0)
    with np.load(tmp_path / "clip.npz") as clip:
        np.testing.assert_array_equal(clip["rotations"], rotations)
        np.testing.assert_array_equal(clip["root"], bn_walk.translations[:, 0].T)
        assert clip["fps"].shape == () and float(clip["fps"]) == 30.0
