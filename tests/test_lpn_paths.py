"""LPN-FiLM on other performers' captures: derived control that keeps to the input's path, and
planted feet that stay planted where the network cannot walk as the input does (CMU 131_02, a
slow start-walk-stop, and a Xia walk, both retargeted to the model rig)."""

from __future__ import annotations

import numpy as np
import pytest

from models.interface import FrameBatch
from models.lpn import kernels
from models.motion.bn_skeleton import HIPS
from models.motion.rate_metrics import planted_slide_p95


@pytest.fixture(scope="module")
def captures(index):
    """CMU 131_02 (8 s) and the first Xia neutral walk, on the model rig at 120 fps."""
    from models.data import load_motion, select
    from models.motion.resample import resample
    from models.motion.retarget import retarget

    out = {}
    for dataset, name in (("cmu", "131_02"), ("xia", "neutral_walk_01_000")):
        clip = next(c for c in select(index, dataset=dataset) if c.name == name)
        motion = load_motion(clip)
        out[dataset] = resample(retarget(motion.slice(0, int(8 * motion.fps)), fps=motion.fps), 120.0)
    return out


def _slides(model, motion, style: str, fps: float) -> tuple[float, float]:
    """Planted-foot slide (p95, leg lengths/s) of the input and of the session's output at `fps`."""
    from clients.rate_bench import at_rate, serve

    m = at_rate(motion, fps)
    root, rot = m.translations[:, HIPS], m.rotations
    out_root, out_rot = serve(model, style, root, rot, fps)
    return planted_slide_p95(m, HIPS, root, rot), planted_slide_p95(m, HIPS, out_root, out_rot)


def test_a_slow_walk_toward_feminine_keeps_its_planted_feet(lpn_model, captures):
    """The CMU walk is slower than any walk LPN-FiLM learned; the output's feet once slid 4x the
    input's (the landing foot gliding along the floor)."""
    slide_in, slide_out = _slides(lpn_model, captures["cmu"], "feminine", 30.0)
    assert slide_out <= 2.0 * slide_in


def test_a_session_served_at_120_fps_starts_with_its_feet_planted(lpn_model, captures):
    """The network's first frames differ from the input's first pose: the feet it stood on stay
    put instead of jumping with the body (a short clip's slide was over twice the input's)."""
    slide_in, slide_out = _slides(lpn_model, captures["xia"], "feminine", 120.0)
    assert slide_out <= 2.0 * slide_in


def test_derived_control_slows_a_character_that_walked_farther_than_a_slow_input(lpn_model):
    """Below the training walks' speeds derived control is the input's velocity slowed by the
    character's lead, how much farther it walked than the input (made up CATCH_UP_S on): 40 cm
    ahead of an input walking 0.3 m/s it is asked for 0.3 - 0.4 / CATCH_UP_S m/s, 1.5 m ahead to
    stand (never to walk back); behind, or level, for the input's own 0.3 m/s, and a shortfall
    fades. A step longer than the input's adds to the lead. An input at walking speed keeps its
    velocity whatever the lead (a style may walk faster), and a client's control is left alone."""
    from models.lpn.runtime import CATCH_UP_S, WALK_SPEED

    model = lpn_model
    speeds = np.array([30.0, 30.0, 30.0, 30.0, 30.0, WALK_SPEED + 10.0, 30.0], np.float32)
    lead = np.array([40.0, 150.0, -40.0, 0.0, 0.0, 40.0, 40.0], np.float32)
    B = len(speeds)
    state = model.init_state(B)
    rest = model.rest_motion()
    root = np.repeat(rest.translations[:1, HIPS], B, axis=0).astype(np.float32)
    rot = np.repeat(rest.rotations[:1], B, axis=0).astype(np.float32)
    yaw = model._facing(model._fk(root, rot)[1])[0]
    forward = np.array([np.sin(yaw), np.cos(yaw)], np.float32)  # world (x, z) of the character's +Z
    tracker = kernels.Tracker(state["frame"] + 5, state["in_pos"], state["in_vel"], lead.copy())
    tracker.in_vel[:] = speeds[:, None] * forward  # the input walks on at these speeds, this frame too
    tracker.in_pos[:] = root[:, [0, 2]] - speeds[:, None] * forward / model.fps
    walked = (speeds / model.fps).astype(np.float32)  # the character's last step as long as the input's ...
    walked[4] += 1.0  # ... but one, a centimetre longer
    given = np.arange(B) == B - 1
    control = np.zeros((B, 5), np.float32)
    control[-1] = [1.0, 0.0, yaw, 0.0, 1.0]
    out = kernels.control_rows(control, given, root, rot, tracker, walked, model._body, model._rules)
    want = [[30.0 - 40.0 / CATCH_UP_S, 0.0], [0.0, 0.0], [30.0, 0.0], [30.0, 0.0]]
    want += [[30.0 - 1.0 / CATCH_UP_S, 0.0], [WALK_SPEED + 10.0, 0.0]]
    np.testing.assert_allclose(out[:-1, :2], want, atol=0.5)
    np.testing.assert_allclose(out[-1], [100.0, 0.0, yaw, 0.0], atol=1e-4)
    fade = np.exp(-1.0 / (model.fps * CATCH_UP_S))
    np.testing.assert_allclose(tracker.lead, [40.0, 150.0, -40.0 * fade, 0.0, 1.0, 40.0, 0.0], atol=1e-3)


def test_a_character_that_lagged_a_reversing_input_follows_it_back(lpn_model):
    """The input side-steps one way at a walk for 5 s, where the character falls behind, then
    slowly back. Behind it in position is ahead along the way back, yet the character walked no
    farther than the input: it follows at the input's pace (once it stood still for the whole
    way back, 0.14 of the input's path; in running sessions, after a long history, whole clips)."""
    model, fps = lpn_model, lpn_model.fps
    rest = model.rest_motion()
    yaw = model._facing(model._fk(rest.translations[:1, HIPS], rest.rotations[:1])[1])[0]
    side = np.array([np.cos(yaw), -np.sin(yaw)])  # world (x, z) of the character's +X
    T = int(5 * fps)
    vel = np.concatenate([np.full(T, 90.0), np.full(T, -40.0)])[:, None] * side  # cm/s
    xz = rest.translations[0, HIPS, [0, 2]] + np.cumsum(vel, axis=0) / fps
    styles = ("elderly", "feminine")
    state, w = model.init_state(len(styles)), np.stack([model.weight_vector({s: 1.0}) for s in styles])
    path = np.zeros((2 * T, len(styles), 2))
    for t in range(2 * T):
        root = np.repeat(rest.translations[:1, HIPS], len(styles), axis=0)
        root[:, [0, 2]] = xz[t]
        out, state = model.step_batch(state, FrameBatch(root, np.repeat(rest.rotations[:1], len(styles), 0)), w)
        path[t] = out.root[:, [0, 2]]
    back = np.linalg.norm(np.diff(path[T:], axis=0), axis=-1).sum(0)
    assert (back >= 0.8 * 40.0 * (T - 1) / fps).all(), back


def test_without_control_it_stays_near_the_input_path(lpn_model, captures):
    """Driven by the CMU walk toward feminine and elderly, the output ends near where the input
    ends: within 1 m after 8 s (it once ended 2.2 m away toward feminine, walking twice as far)."""
    from clients.rate_bench import at_rate

    m = at_rate(captures["cmu"], 30.0)
    for style in ("feminine", "elderly"):
        state, w = lpn_model.init_state(1), lpn_model.weight_vector({style: 1.0})[None]
        for t in range(m.num_frames):
            out, state = lpn_model.step_batch(
                state, FrameBatch(m.translations[t : t + 1, HIPS], m.rotations[t : t + 1]), w
            )
        end = np.linalg.norm(out.root[0, [0, 2]] - m.translations[-1, HIPS, [0, 2]])
        assert end < 100.0, style
