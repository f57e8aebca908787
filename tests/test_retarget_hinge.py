"""A near-straight limb's twist falls back toward the client's own hinge axis, learned per stream
(`retarget.HINGE_FALLBACK`, `FrameRetargeter.init_state`): a straightening limb keeps its twist on a
real capture, and a session's snapshot carries that state so a resume continues bit for bit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.data import load_motion, select
from models.motion.resample import resample
from models.motion.retarget_stream import FrameRetargeter
from models.motion.rotations import quat_to_matrix
from models.settings import get_settings


def _world(rotations: np.ndarray, parents: np.ndarray) -> np.ndarray:
    local = quat_to_matrix(rotations)
    world = local.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            world[:, j] = world[:, p] @ local[:, j]
    return world


def twist_turn(fr: FrameRetargeter, motion, limb: str, child: str, role: str) -> np.ndarray:
    """(F - 1,) degrees per frame: how far BN's limb joint turns about its bone against the
    client's joint of the same limb. A hinge whose axis keeps its place in the client's limb turns
    by nothing; a twist that falls back to an axis the client's limb does not carry turns as the
    limb straightens."""
    _, bn = fr.to_model(motion.translations[:, fr.humanoid.translated], motion.rotations)
    sk = fr.rig.skeleton
    gb = _world(bn, sk.parents)[:, sk.index(limb)]
    gc = fr._axes @ _world(motion.rotations, motion.skeleton.parents)[:, fr.humanoid.roles[role]]
    rel = np.swapaxes(gc, -1, -2) @ gb  # BN's limb frame in the client's
    b = sk.offsets[sk.index(child)] / np.linalg.norm(sk.offsets[sk.index(child)])
    side = np.cross(b, [0.0, 0.0, 1.0] if abs(b[2]) < 0.9 else [1.0, 0.0, 0.0])
    bone, r = rel @ b, rel @ (side / np.linalg.norm(side))
    e = np.eye(3)[np.argmin(np.abs(bone.mean(0)))]  # a client axis away from the bone, made perpendicular
    e = e - np.sum(bone * e, -1, keepdims=True) * bone
    e /= np.linalg.norm(e, axis=-1, keepdims=True)
    angle = np.unwrap(np.arctan2(np.sum(r * np.cross(bone, e), -1), np.sum(r * e, -1)))
    return np.degrees(np.abs(np.diff(angle)))


@pytest.mark.parametrize("fps,most", [(30.0, 15.0), (120.0, 5.0)])
def test_a_straightening_arm_keeps_its_twist(index, fps, most):
    """The Xia punch straightens its left arm within a few frames: with the natural axis as the
    fallback, BN's upper arm turned 35 (30 fps) and 10.5 (120 fps) degrees in one frame against
    the client's arm; with the learned axis 12 and 3.3."""
    motion = resample(load_motion(select(index, dataset="xia", name="depressed_punch_18_000")[0]), fps)
    fr = FrameRetargeter(motion.skeleton)
    assert twist_turn(fr, motion, "UpperArm_L", "LowerArm_L", "upperarm_l").max() < most


def test_the_hinge_state_learns_the_axis_in_the_clients_joint(index):
    """Fed a walk, each limb's state holds a unit-ish axis far from its first guess' weight: the
    bent frames count; a fresh state starts from nothing, and one stream's state is its own."""
    motion = load_motion(select(index, dataset="cmu", name="131_02")[0]).slice(0, 120)
    fr = FrameRetargeter(motion.skeleton)
    state = fr.init_state(2)
    assert not state.any()
    root, rot = motion.translations[:, fr.humanoid.translated], motion.rotations
    for t in range(60):
        fr.to_model(root[[t, 60 + t]], rot[[t, 60 + t]], state)
    assert (state[:, :, 3] > 1.0).all()  # the prior (1) plus sin^2 of each frame's bend
    assert not np.array_equal(state[0], state[1])
    alone = fr.init_state()
    fr.to_model(root[60:], rot[60:], alone)
    np.testing.assert_allclose(alone[0], state[1], rtol=1e-12, atol=1e-12)


@pytest.fixture(scope="module")
def lti():
    from models.registry import load_models

    return load_models(get_settings().weights_dir)["lti"]


def test_a_resumed_session_continues_the_hinge_state_exactly(lti, index):
    """A CMU walk streamed through the service's session path (the client's rig retargeted both
    ways): snapshot after frame 40, store as bytes, restore; the hinge state comes back equal and
    every later reply equals the uninterrupted session's, bit for bit. A snapshot saved before
    sessions kept it resumes with a fresh state."""
    from models.interface import FrameBatch, style_vector
    from models.motion.humanoid import humanoid_rig
    from service.sessions import Session, Snapshot
    from service.skeletons import Retarget

    motion = load_motion(select(index, dataset="cmu", name="131_02")[0]).slice(0, 70)
    adapter = Retarget(humanoid_rig(motion.skeleton))
    root, rot = motion.translations[:, 0], motion.rotations
    weights = {"elderly": 1.0}

    def run(s: Session, frames: range) -> list:
        out = []
        for t in frames:
            r, q = adapter.to_model(root[t], rot[t], s.hinges)
            for step_root, step_rot in s.model_inputs(r, q):
                o, s.state = lti.step_batch(
                    s.state, FrameBatch(step_root[None], step_rot[None]), style_vector(lti, weights)[None]
                )
                s.hold(o.root[0], o.rotations[0], r, q)
            out.append(adapter.from_model(*s.held_output(), rot[t], s.hinges))
        return out

    def fresh() -> Session:
        return Session(lti, "cmu", 30.0, "binary", weights, lti.init_state(1))

    whole = run(fresh(), range(70))
    first = fresh()
    run(first, range(41))
    assert first.hinges[0, :, 3].min() > 1.0  # learned something
    again = Session.restore(Snapshot.from_bytes(first.snapshot().to_bytes()), lti, queue_size=8)
    assert np.array_equal(again.hinges, first.hinges)
    json_again = Session.restore(Snapshot.from_json(first.snapshot().to_json()), lti, queue_size=8)
    assert np.array_equal(json_again.hinges, first.hinges)
    rest = run(again, range(41, 70))
    for (a_root, a_rot), (b_root, b_rot) in zip(whole[41:], rest, strict=True):
        assert np.array_equal(a_root, b_root) and np.array_equal(a_rot, b_rot)

    old = json.loads(first.snapshot().to_json())
    del old["retarget"]  # as stored before the state existed
    assert not Session.restore(Snapshot.from_json(json.dumps(old)), lti, queue_size=8).hinges.any()


def test_retargeted_crowd_characters_each_keep_their_own_hinge_state(lti, index):
    """Two CMU characters in one crowd, at different places in a walk, and a third joining later:
    each reply equals that character's own session's, bit for bit (each crowd row carries its own
    hinge state, as a session does)."""
    from clients.sdk import Character, Client

    from .live_server import live_server
    from .rigs import as_bvh_file

    header, motion = as_bvh_file(load_motion(select(index, dataset="cmu", name="131_02")[0]).slice(0, 240))
    starts, ticks = (0, 90, 200), 16
    model = {"lti": lti}

    def alone(start: int, first: int) -> list[np.ndarray]:
        with Client(base, timeout=30) as client, client.session(model="lti", style="elderly", bvh_header=header) as s:
            return [
                s.stylise(motion.translations[start + t, 0], motion.rotations[start + t]).rotations
                for t in range(first, ticks)
            ]

    with live_server(model, idle_timeout_s=30, max_characters=8, token_max_characters=8) as (base, _app):
        got: dict[int, list[np.ndarray]] = {0: [], 1: [], 2: []}
        chars = [Character(i, "lti", "elderly", bvh_header=header) for i in range(2)]
        with Client(base, timeout=30) as client, client.crowd(chars) as crowd:
            for t in range(ticks):
                if t == 5:
                    crowd.join([Character(2, "lti", "elderly", bvh_header=header)])
                ids = [0, 1, 2] if t >= 5 else [0, 1]
                frames = [starts[i] + t for i in ids]
                out = crowd.tick(ids, motion.translations[frames, 0], motion.rotations[frames])
                for i in ids:
                    got[i].append(out.frame(i)[1].copy())
            assert crowd.errors == []
        for i in range(3):
            want = alone(starts[i], 5 if i == 2 else 0)
            assert np.array_equal(np.array(got[i]), np.array(want, np.float32)), i
