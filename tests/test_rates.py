"""Every frame rate from 24 to 120 fps served at its own rate (`models.motion.rate`): the maths
on its own, then a session on a real CMU capture at 30, 60 and 120 fps, driven as the service
drives it (`clients.rate_bench.serve`)."""

from __future__ import annotations

import numpy as np
import pytest

from models.motion import rate
from models.motion.bn_skeleton import BODY, HIPS
from models.motion.rotations import quat_exp
from models.settings import get_settings

RATES = (24.0, 25.0, 30.0, 50.0, 60.0, 90.0, 120.0)


@pytest.mark.parametrize("fps", RATES)
def test_each_model_step_takes_the_input_at_its_own_time_and_each_reply_the_stated_delay(fps):
    """Driven frame by frame: step j happens on the first frame at or after j / 30 s, on the pose
    interpolated at exactly j / 30 s between the previous frame and this one (no look-ahead), and
    each frame's reply is the model's output at exactly its time less the stated delay, between
    the two latest steps."""
    model_fps, frames = 30.0, 400
    lag = rate.output_lag(model_fps, fps)
    assert 0.0 <= lag <= 1.0
    clock, steps_so_far = np.array([-1.0]), 0
    for k in range(frames):
        t, before = k / fps, clock[0]
        clock, steps, weights = rate.steps_due(clock, model_fps / fps)
        for i in range(int(steps[0])):
            j = steps_so_far + i
            at = t if k == 0 else (k - 1 + weights[0, i]) / fps
            assert at == pytest.approx(j / model_fps, abs=1e-9), (k, j, before)
        steps_so_far += int(steps[0])
        latest = steps_so_far - 1
        assert latest / model_fps <= t + 1e-9 < (latest + 1) / model_fps  # every step due has run
        u = rate.output_weight(clock, lag)[0]
        shown = (latest - 1 + u) / model_fps
        assert shown == pytest.approx(t - lag / model_fps, abs=1e-9) or k == 0


def test_the_stated_delays():
    assert [rate.output_delay_s(30.0, f) * 1000 for f in (30.0, 60.0, 120.0, 24.0)] == pytest.approx(
        [0.0, 50 / 3, 25.0, 25.0]
    )
    assert rate.output_lag(30.0, 29.97) == 1.0  # no small fraction: one model frame


def test_the_parabola_passes_through_the_outputs_and_follows_a_steady_acceleration():
    """A root quadratic in time, and a rotation about one axis whose angle is (up to 0.7 rad, 20
    rad/s, a model frame): the curve through three outputs follows them in between, the root
    exactly and the rotation within 0.1 degree where a straight line is off by over a degree;
    its ends are the two latest outputs, the latest exactly."""
    from models.motion.resample import slerp

    axis = np.array([0.3, 0.9, -0.3]) / np.linalg.norm([0.3, 0.9, -0.3])

    def pose(t: float) -> tuple[np.ndarray, np.ndarray]:
        return np.array([t * t, 2 * t, -t]), quat_exp(axis * (0.2 + 0.3 * t + 0.1 * t * t))[None]

    def degrees(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.degrees(2 * np.arccos(min(1.0, abs(float(np.dot(a, b)))))))

    roots = np.stack([pose(t)[0] for t in (0.0, 1.0, 2.0)])[None]
    rots = np.stack([pose(t)[1] for t in (0.0, 1.0, 2.0)])[None]
    for u in (0.0, 0.25, 0.5, 0.75, 1.0):
        root, rot = rate.interpolate(roots, rots, np.array([u]))
        want_root, want_rot = pose(1.0 + u)
        np.testing.assert_allclose(root[0], want_root, atol=1e-12)
        assert degrees(rot[0, 0], want_rot[0]) < 0.1
        if 0 < u < 1:
            line = slerp(rots[0, 1], rots[0, 2], np.array([[u]]))[0]
            assert degrees(line, want_rot[0]) > 1.0
    root, rot = rate.interpolate(roots, rots, np.array([1.0]))
    assert np.array_equal(root[0], roots[0, 2]) and np.array_equal(rot[0], rots[0, 2])


def test_the_input_at_a_model_step_is_the_slerp_between_the_frames_around_it():
    from models.motion.resample import slerp

    rng = np.random.default_rng(3)
    q0, q1 = quat_exp(rng.normal(size=(4, 22, 3))), quat_exp(rng.normal(size=(4, 22, 3)))
    r0, r1 = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    w = np.array([0.0, 0.3, 0.8, 1.0])
    root, rot = rate.blend(r0, q0, r1, q1, w)
    np.testing.assert_allclose(root, r0 + w[:, None] * (r1 - r0), atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(rot * slerp(q0, q1, w[:, None, None]), -1)), 1.0, atol=1e-12)
    assert np.array_equal(rot[0], q0[0]) and np.array_equal(rot[3], q1[3])


# ---- a session on a real capture ---------------------------------------------------------


@pytest.fixture(scope="module")
def lti():
    from models.registry import load_models

    return load_models(get_settings().weights_dir)["lti"]


@pytest.fixture(scope="module")
def cmu_walk_120(index):
    """CMU 131_02 (start, walk, stop), 5 s at 120 fps, retargeted to the model rig."""
    from models.data import load_motion, select
    from models.motion.retarget import retarget

    clip = next(c for c in select(index, dataset="cmu") if c.name == "131_02")
    motion = load_motion(clip)
    return retarget(motion.slice(0, 600), fps=motion.fps)


@pytest.fixture(scope="module")
def served(lti, cmu_walk_120):
    """{fps: (input, out roots, out rotations)} for the walk served at 30, 60 and 120 fps, and the
    same session held the old way (sample-and-hold) at 120 fps, under "held"."""
    from clients.rate_bench import at_rate, serve, serve_held

    style = "elderly"
    out = {}
    for fps in (30.0, 60.0, 120.0):
        m = at_rate(cmu_walk_120, fps)
        out[fps] = (m, *serve(lti, style, m.translations[:, HIPS], m.rotations, fps))
    out["held"] = (
        cmu_walk_120,
        *serve_held(lti, style, cmu_walk_120.translations[:, HIPS], cmu_walk_120.rotations, 120.0),
    )
    return out


@pytest.mark.parametrize("fps", [30.0, 60.0, 120.0])
def test_every_frame_gets_its_own_pose_smoothly(served, fps):
    """One reply per frame; at 60 and 120 fps a new pose on every frame (none held); rotation
    jitter within 1.5x the input's and planted-foot slide within 2x."""
    from models.motion.rate_metrics import jitter, planted_slide_p95

    motion, root, rot = served[fps]
    assert len(rot) == motion.num_frames
    change = np.abs(np.diff(rot[:, BODY], axis=0)).max(axis=(1, 2))
    assert (change[4:] > 1e-7).all()  # after the first steps (the first output stands for earlier ones)
    assert jitter(rot, fps, BODY) <= 1.5 * jitter(motion.rotations, fps, BODY)
    assert planted_slide_p95(motion, HIPS, root, rot) <= 2.0 * planted_slide_p95(
        motion, HIPS, motion.translations[:, HIPS], motion.rotations
    )


@pytest.mark.parametrize("fps", [60.0, 120.0])
def test_the_stream_adds_only_the_stated_delay_to_the_models_own_output(served, fps):
    """Served at 60 or 120 fps, the output trails what the model makes at its own 30 fps by the
    stated delay (within 0.75 frames): the rate adapter neither smooths nor adds lag."""
    from models.motion.rate_metrics import lag_frames
    from models.motion.resample import resample
    from models.motion.skeleton import Motion

    motion, _, rot = served[fps]
    base, _, own = served[30.0]
    own_at_fps = resample(Motion(base.skeleton, own, base.translations, 30.0, base.euler_orders), fps).rotations
    n = min(len(own_at_fps), len(rot))
    lag = lag_frames(own_at_fps[:n, BODY], rot[:n, BODY], max_lag=int(fps))
    assert abs(lag - rate.output_lag(30.0, fps) * fps / 30.0) < 0.75


@pytest.mark.parametrize("fps", [30.0, 60.0, 120.0])
def test_the_output_keeps_the_inputs_timing_within_one_model_frame(served, fps):
    """Issue 45's figure: the output's joint rotations trail the input's by at most one model
    frame, the stated delay included. It measures the style's own timing too, once the model
    styles the input rather than handing it back."""
    from models.motion.rate_metrics import lag_frames

    motion, _, rot = served[fps]
    # measured 0.26 and 3.97 frames at 30 and 120 fps: at 120 the stated 0.75 model frames and
    # LTI's own trailing toward elderly (the legs' 4.39 frames, the feet's 3.08) leave 0.03 to spare
    assert lag_frames(motion.rotations[:, BODY], rot[:, BODY], max_lag=int(fps)) <= fps / 30.0


def test_sample_and_hold_fails_what_interpolation_passes(served):
    """The same checks on what was served before (the pose held for 4 frames at 120 fps) fail:
    the figures above can tell the two apart."""
    from models.motion.rate_metrics import jitter, planted_slide_p95

    motion, root, rot = served["held"]
    assert jitter(rot, 120.0, BODY) > 3 * jitter(motion.rotations, 120.0, BODY)
    assert planted_slide_p95(motion, HIPS, root, rot) > 2.0 * planted_slide_p95(
        motion, HIPS, motion.translations[:, HIPS], motion.rotations
    )


def test_a_snapshot_taken_between_model_steps_resumes_exactly(lti, cmu_walk_120):
    """At 120 fps, snapshot after frame 50 (two frames into a model period), store, restore on a
    fresh session: every later reply equals the uninterrupted session's, bit for bit."""
    from models.interface import FrameBatch, style_vector
    from service.sessions import Session, Snapshot

    root, rot = cmu_walk_120.translations[:90, HIPS], cmu_walk_120.rotations[:90]
    w = style_vector(lti, {"elderly": 1.0})[None]

    def run(s: Session, frames: range) -> list:
        out = []
        for t in frames:
            for r, q in s.model_inputs(root[t], rot[t]):
                o, s.state = lti.step_batch(s.state, FrameBatch(r[None], q[None]), w)
                s.hold(o.root[0], o.rotations[0], root[t], rot[t])
            out.append(s.held_output())
        return out

    def fresh() -> Session:
        return Session(lti, "bandai-namco", 120.0, "binary", {"elderly": 1.0}, lti.init_state(1))

    whole = run(fresh(), range(90))
    first = fresh()
    run(first, range(51))
    assert 0.0 < first.clock < 1.0  # between model steps
    again = Session.restore(Snapshot.from_bytes(first.snapshot().to_bytes()), lti, queue_size=8)
    rest = run(again, range(51, 90))
    for (a_root, a_rot), (b_root, b_rot) in zip(whole[51:], rest, strict=True):
        assert np.array_equal(a_root, b_root) and np.array_equal(a_rot, b_rot)


def test_a_snapshot_from_before_interpolation_starts_the_rate_afresh(lti, cmu_walk_120):
    """A snapshot stored by a replica that held one output (no input pose, no earlier outputs):
    the session resumes its model state, and its next frame steps the model anew."""
    from service.sessions import Session

    s = Session(lti, "bandai-namco", 120.0, "binary", {"elderly": 1.0}, lti.init_state(1))
    snap = s.snapshot()
    snap.clock = 0.5
    snap.held = {"root": np.zeros(3), "rotations": cmu_walk_120.rotations[0], "input_root": np.zeros(3)}
    again = Session.restore(snap, lti, queue_size=8)
    assert again.held is None
    inputs = again.model_inputs(cmu_walk_120.translations[1, HIPS], cmu_walk_120.rotations[1])
    assert len(inputs) == 1 and np.array_equal(inputs[0][1], cmu_walk_120.rotations[1])


def test_the_load_test_sends_real_motion_at_60_fps():
    """At 60 fps the load test (sessions and crowds) sends a real capture at 60 fps: a new pose
    in every frame, where the 30 fps walk it sent before repeated every other one."""
    from clients.loadtest import load_frames, real_frames

    _, rot = load_frames(240, 60.0)
    assert (np.abs(np.diff(rot, axis=0)).max(axis=(1, 2)) > 1e-4).all()
    _, before = real_frames(240, 60.0)
    assert (np.abs(np.diff(before, axis=0)).max(axis=(1, 2)) == 0).sum() >= 100
