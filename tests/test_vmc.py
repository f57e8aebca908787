"""VMC bridge: its OSC codec against python-osc, the avatar's own rig, and end to end over UDP on
loopback through a live server, with a VMC sender made from a real Bandai Namco walk
(tests/rigs.py `EXTRA_SPECS["vmc"]`: Unity bone names, UpperChest, eyes, fingers, metres, the
normalised T-pose), written in Unity's left-handed axes as VMC senders do."""

from __future__ import annotations

import socket
from contextlib import contextmanager
from functools import lru_cache

import numpy as np
import pytest
from pythonosc import osc_packet
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from clients import vmc_osc as osc
from clients.vmc import (
    BODY_BONES,
    BONE_GROUPS,
    StyleLink,
    VmcBridge,
    VmcState,
    avatar_rig,
    model_input,
    parse_bones,
    session_opener,
    unity_output,
)
from models.motion import bvh
from models.motion.humanoid import RigError
from models.motion.skeleton import Motion, from_bvh
from models.settings import get_settings

from .clips import angle_deg
from .rigs import EXTRA_SPECS, as_bvh_file, make_rig, stream

FRAMES = 30
UNITY = np.diag([-1.0, 1.0, 1.0])  # right-handed <-> Unity: mirror X
BLEND = [
    ("/VMC/Ext/Blend/Val", ["A", 0.25]),
    ("/VMC/Ext/Blend/Val", ["Blink_L", 1.0]),
    ("/VMC/Ext/Blend/Apply", []),
    ("/VMC/Ext/Tra/Pos", ["tracker1", 0.1, 1.2, 0.3, 0.0, 0.0, 0.0, 1.0]),
    ("/VMC/Ext/Cam", ["cam", 0.0, 1.5, -2.0, 0.0, 0.0, 0.0, 1.0, 60.0]),
]


# --------------------------------------------------------------------------- a VMC sender


def _message(address: str, args) -> bytes:
    msg = OscMessageBuilder(address=address)
    for a in args:
        msg.add_arg(a)
    return msg.build().dgram


def _bundle(messages) -> bytes:
    b = OscBundleBuilder(IMMEDIATELY)
    for address, args in messages:
        msg = OscMessageBuilder(address=address)
        for a in args:
            msg.add_arg(a)
        b.add_content(msg.build())
    return b.build().dgram


class Sender:
    """A made-rig motion as a VMC sender sends it: per frame the root, every bone's Unity local
    position and rotation (mirrored from the right-handed made rig), blend shapes, a tracker, OK, T."""

    def __init__(self, motion: Motion) -> None:
        self.motion = motion
        unity = _mirror(motion, UNITY)
        self.names = list(motion.skeleton.names)
        self.pos, self.rot = unity.translations, unity.rotations

    def messages(self, t: int, bones: list[str] | None = None, extra=BLEND) -> list:
        names = self.names if bones is None else bones
        out = [("/VMC/Ext/Root/Pos", ["root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])]
        for n in names:
            j = self.names.index(n)
            out.append(("/VMC/Ext/Bone/Pos", [n, *map(float, self.pos[t, j]), *map(float, self.rot[t, j])]))
        return out + list(extra) + [("/VMC/Ext/OK", [1]), ("/VMC/Ext/T", [t / 30.0])]

    def bundle(self, t: int, **kw) -> bytes:
        return _bundle(self.messages(t, **kw))


def _mirror(motion: Motion, m: np.ndarray) -> Motion:
    from .rigs import mirrored

    return mirrored(motion, m)


def _parse(datagrams: list[bytes]) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[tuple[str, list]]]:
    """Bones {name: (pos, rot)} and the other messages of a frame's output, read with python-osc."""
    bones, other = {}, []
    for d in datagrams:
        for timed in osc_packet.OscPacket(d).messages:
            m = timed.message
            if m.address == "/VMC/Ext/Bone/Pos":
                bones[m.params[0]] = (np.array(m.params[1:4]), np.array(m.params[4:8]))
            else:
                other.append((m.address, list(m.params)))
    return bones, other


@pytest.fixture(scope="module")
def avatar(bn_walk) -> Motion:
    return make_rig(bn_walk.slice(0, FRAMES), EXTRA_SPECS["vmc"])


@lru_cache(maxsize=1)
def _lti():
    from models.lti import load

    return load(get_settings().weights_dir / "lti")


@pytest.fixture(scope="module")
def server():
    from .live_server import live_server

    with live_server({"lti": _lti()}) as (base, _):
        yield base


@contextmanager
def _server_on(port: int, models: dict):
    """A live server on a fixed port (so that a test can restart it where the bridge expects it)."""
    from .live_server import live_server

    with live_server(models, port) as (base, _):
        yield base


@contextmanager
def _bridge(url: str | None, reconnect_timeout: float = 60.0, **kw):
    """A bridge on loopback (link to `url`, or none: pass-through) and a socket receiving its output."""
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(20)
    link = (
        StyleLink(session_opener(url, "lti", "elderly", fps=30.0, reconnect_timeout=reconnect_timeout)) if url else None
    )
    bridge = VmcBridge(link, sink.getsockname(), ("127.0.0.1", 0), **kw)
    thread = bridge.start()
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        yield bridge, sender, sink
    finally:
        bridge.close()
        thread.join(5)
        sender.close()
        sink.close()


def _round(bridge: VmcBridge, sender: socket.socket, sink: socket.socket, data: bytes) -> list[bytes]:
    """Send one frame, return the datagram(s) that came back for it."""
    sender.sendto(data, bridge.address)
    return [sink.recv(65536)]


def _stream_styled(bridge, sender, sink, source: Sender, frames: int = FRAMES, **kw) -> list:
    """Frames through the bridge once its session is open (the first frames open it)."""
    out = []
    if bridge.link is not None and not bridge.link.ready:  # a first frame (passed through) opens the session
        _round(bridge, sender, sink, source.bundle(0, **kw))
        assert bridge.link.wait_ready(30), "no session opened"
    styled_before = bridge.stats.styled
    for t in range(frames):
        out.append(_parse(_round(bridge, sender, sink, source.bundle(t, **kw))))
    assert bridge.stats.styled - styled_before == (frames if bridge.link else 0)
    return out


def _direct(url: str, motion: Motion) -> dict:
    """The same avatar streamed straight to the service as a right-handed BVH rig (no bridge)."""
    header, m = as_bvh_file(motion)
    hips = m.skeleton.index("Hips")
    _, root, rot = stream(url, {"bvh_header": header, "fps": 30.0}, m.translations[:, hips], m.rotations)
    return {"names": list(m.skeleton.names), "root": root, "rotations": rot}


# --------------------------------------------------------------------------- codec


def test_codec_reads_and_writes_what_python_osc_does():
    rng = np.random.default_rng(0)
    values = rng.normal(size=(3, 7)).astype(np.float32).astype(np.float64)
    enc = osc.PoseEncoder("/VMC/Ext/Bone/Pos")
    extra = osc.element(osc.encode_message("/VMC/Ext/Blend/Val", ["Joy", 0.5]))
    (data,) = osc.bundles(enc.elements(["Hips", "LeftHand", "Spine"], values) + [extra])
    msgs = [t.message for t in osc_packet.OscPacket(data).messages]
    assert [m.params[0] for m in msgs] == ["Hips", "LeftHand", "Spine", "Joy"]
    np.testing.assert_array_equal(np.array([m.params[1:8] for m in msgs[:3]]), values)
    assert msgs[3].address == "/VMC/Ext/Blend/Val" and msgs[3].params[1] == 0.5
    # python-osc's packets -> ours: nested bundles flattened, raw bytes kept, any argument types
    inner = OscBundleBuilder(IMMEDIATELY)
    inner.add_content(OscMessageBuilder("/VMC/Ext/Bone/Pos").build())
    b = OscBundleBuilder(IMMEDIATELY)
    pose = _message("/VMC/Ext/Bone/Pos", ["Head", *map(float, values[0])])
    odd = _message("/VMC/Ext/Bone/Pos", ["Neck", 1, 2, 3, 0, 0, 0, 1])  # ints: decoded the slow way
    other = _message("/x", ["s", 3, 2.5, b"blob", True])
    for m in (pose, odd, other):
        b.add_content(osc_packet.OscPacket(m).messages[0].message)
    b.add_content(inner.build())
    parts = list(osc.elements(b.build().dgram))
    assert parts[:3] == [pose, odd, other] and len(parts) == 4
    assert osc.decode_pose(pose) == ("Head", tuple(np.float32(values[0]).tolist()))
    assert osc.decode_pose(odd) == ("Neck", (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0))
    assert osc.decode_pose(parts[3]) is None  # a pose address without arguments
    assert osc.decode_args(other) == ["s", 3, 2.5, b"blob", True]
    with pytest.raises(osc.OscError):
        list(osc.elements(osc.BUNDLE_TAG + osc.IMMEDIATELY + b"\x00\x00\x01\x00abc"))
    big = osc.bundles([extra] * 3000)  # ~100 kB: split into datagrams that fit
    assert len(big) == 2 and all(len(d) <= osc.MAX_DATAGRAM for d in big)
    assert sum(len(osc_packet.OscPacket(d).messages) for d in big) == 3000


def test_bone_mask_names_and_groups():
    assert parse_bones("body") == frozenset(BODY_BONES)
    assert parse_bones("upper") == frozenset(BONE_GROUPS["upper"]) and "Hips" not in parse_bones("upper")
    assert parse_bones("body,-legs,-Hips") == parse_bones("upper")
    assert parse_bones("arms, Head") == frozenset(BONE_GROUPS["arms"]) | {"Head"}
    with pytest.raises(ValueError, match="Tail"):
        parse_bones("upper,Tail")


# --------------------------------------------------------------------------- the avatar's rig


def test_the_rig_is_the_avatars_own(avatar):
    source = Sender(avatar)
    state = VmcState()
    state.update(source.names, np.concatenate([source.pos[0], source.rot[0]], axis=1), 0.0)
    rig = avatar_rig(state.body())
    assert set(rig.bones) == set(BODY_BONES) and rig.bones[0] == "Hips"  # eyes and fingers are not the body
    assert rig.report["preset"] == "unity" and rig.report["up"] == "y" and rig.report["units"] == "m"
    sk = avatar.skeleton
    leg = sum(np.linalg.norm(sk.offsets[sk.index(n)]) for n in ("LeftLowerLeg", "LeftFoot"))
    assert rig.report["leg_length"] == pytest.approx(leg, rel=1e-6)  # the avatar's, not the model's
    header = from_bvh(bvh.parse(rig.header + "MOTION\nFrames: 0\nFrame Time: 0.0166667\n")).skeleton
    for name in rig.bones[1:]:  # offsets as sent, mirrored to right-handed
        np.testing.assert_allclose(header.offsets[header.index(name)], sk.offsets[sk.index(name)], atol=1e-7)
    # the frame conversion is exact both ways, with an avatar root turned and moved
    state.root_pos, state.root_rot = np.array([0.3, 0.1, -2.0]), np.array([0.0, np.sin(0.4), 0.0, np.cos(0.4)])
    slots = np.array([state.slot[b] for b in rig.bones])
    root, rot = model_input(slots, state)
    hips, back = unity_output(state, root, rot)
    np.testing.assert_allclose(hips, state.pos[slots[0]], atol=1e-12)
    np.testing.assert_allclose(
        back, state.rot[slots] / np.linalg.norm(state.rot[slots], axis=1, keepdims=True), atol=1e-12
    )
    legless = {b: p for b, p in state.body().items() if "Leg" not in b}
    with pytest.raises(RigError, match="upperleg_l"):
        avatar_rig(legless)


# --------------------------------------------------------------------------- end to end


def test_bridge_restyles_on_the_avatars_proportions_and_passes_the_rest(server, avatar):
    source = Sender(avatar)
    with _bridge(server) as (bridge, sender, sink):
        frames = _stream_styled(bridge, sender, sink, source)
    want = _direct(server, avatar)
    for t, (bones, other) in enumerate(frames):
        assert set(bones) == set(source.names)  # body, eyes and fingers
        for name in BODY_BONES:
            j = want["names"].index(name)
            q = bones[name][1] * [1, -1, -1, 1]  # back to right-handed
            assert angle_deg(q, want["rotations"][t, j]) < 0.05, (t, name)
        np.testing.assert_allclose(bones["Hips"][0] * [-1, 1, 1], want["root"][t], atol=2e-5)  # metres
        for name in ("LeftEye", "LeftIndexProximal", "RightThumbProximal"):  # not restyled: as sent
            j = source.names.index(name)
            np.testing.assert_array_equal(bones[name][1], np.float32(source.rot[t, j]))
        sent = [m for m in source.messages(t) if m[0] not in ("/VMC/Ext/Root/Pos", "/VMC/Ext/Bone/Pos")]
        assert [(a, [np.float32(v) if isinstance(v, float) else v for v in args]) for a, args in other[1:]] == [
            (a, [np.float32(v) if isinstance(v, float) else v for v in args]) for a, args in sent
        ]
        assert other[0][0] == "/VMC/Ext/Root/Pos"
    moved = max(
        angle_deg(frames[t][0]["LeftUpperArm"][1], source.rot[t, source.names.index("LeftUpperArm")])
        for t in range(FRAMES)
    )
    assert moved > 2.0  # the style is there


def test_a_smaller_avatar_moves_in_proportion(server, avatar):
    """The same walk on an avatar 0.7 times the size: every joint where the full-size avatar's
    is, times 0.7 (the mapping is scale-free; the bridge sends the avatar's own offsets)."""
    small = Motion(
        type(avatar.skeleton)(
            avatar.skeleton.names, avatar.skeleton.parents, avatar.skeleton.offsets * 0.7, avatar.skeleton.end_sites
        ),
        avatar.rotations,
        avatar.translations * 0.7,
        avatar.fps,
    )
    out = []
    for m in (avatar, small):
        with _bridge(server) as (bridge, sender, sink):
            frames = _stream_styled(bridge, sender, sink, Sender(m))
            assert bridge.rig.report["leg_length"] == pytest.approx(_leg(m), rel=1e-5)
        out.append(frames)
    for (big, _), (little, _) in zip(*out):
        np.testing.assert_allclose(little["Hips"][0], 0.7 * big["Hips"][0], atol=2e-5)
        for name in BODY_BONES:
            assert angle_deg(little[name][1], big[name][1]) < 0.05, name


def _leg(m: Motion) -> float:
    sk = m.skeleton
    return float(sum(np.linalg.norm(sk.offsets[sk.index(n)]) for n in ("LeftLowerLeg", "LeftFoot")))


def test_bone_mask_restyles_the_chosen_bones_only(server, avatar):
    source = Sender(avatar)
    with _bridge(server, bones=parse_bones("upper")) as (bridge, sender, sink):
        frames = _stream_styled(bridge, sender, sink, source)
    upper_moved = 0.0
    for t, (bones, _) in enumerate(frames):
        for name in BONE_GROUPS["lower"]:  # legs and hips: exactly what the sender sent
            j = source.names.index(name)
            np.testing.assert_array_equal(bones[name][1], np.float32(source.rot[t, j]))
            np.testing.assert_array_equal(bones[name][0], np.float32(source.pos[t, j]))
        upper_moved = max(
            upper_moved, angle_deg(bones["LeftUpperArm"][1], source.rot[t, source.names.index("LeftUpperArm")])
        )
    assert upper_moved > 2.0


def test_missing_bones_go_back_to_rest_after_the_timeout(avatar):
    """A sender that stops sending the legs: they hold for the timeout, then rest (identity);
    sent again, they are back. A fake clock: no sleeping."""
    source = Sender(avatar)
    upper = [n for n in source.names if "Leg" not in n and "Foot" not in n and "Toes" not in n]
    with _bridge(None, bone_timeout_s=0.5) as (bridge, _, _):
        bones, _ = _parse(bridge.handle(source.bundle(0), now=10.0))
        knee = source.names.index("LeftLowerLeg")
        np.testing.assert_array_equal(bones["LeftLowerLeg"][1], np.float32(source.rot[0, knee]))
        bones, _ = _parse(bridge.handle(source.bundle(1, bones=upper), now=10.4))
        np.testing.assert_array_equal(bones["LeftLowerLeg"][1], np.float32(source.rot[0, knee]))  # held
        bones, _ = _parse(bridge.handle(source.bundle(2, bones=upper), now=10.6))
        np.testing.assert_array_equal(bones["LeftLowerLeg"][1], [0, 0, 0, 1])  # reset
        np.testing.assert_allclose(bones["LeftLowerLeg"][0], np.float32(source.pos[0, knee]))  # at its rest offset
        np.testing.assert_array_equal(bones["Head"][1], np.float32(source.rot[2, source.names.index("Head")]))
        bones, _ = _parse(bridge.handle(source.bundle(3), now=10.7))
        np.testing.assert_array_equal(bones["LeftLowerLeg"][1], np.float32(source.rot[3, knee]))


def test_loose_messages_and_non_pose_bundles(avatar):
    source = Sender(avatar)
    with _bridge(None) as (bridge, _, _):
        out = []
        for address, args in source.messages(0):  # loose: the frame completes on /VMC/Ext/T
            out += bridge.handle(_message(address, args), now=1.0)
        blend = [d for d in out if osc.address(d) == b"/VMC/Ext/Blend/Val"]
        assert len(out) == 1 and not blend  # blend shapes inside a loose frame go out with it
        bones, other = _parse(out)
        assert set(bones) == set(source.names) and [a for a, _ in other].count("/VMC/Ext/Blend/Val") == 2
        only_blend = _bundle(BLEND[:2])  # a bundle without pose messages goes on as it came
        assert bridge.handle(only_blend, now=1.1) == [only_blend]
        assert bridge.handle(b"not osc", now=1.2) == [] and bridge.receiver.bad == 1


@pytest.mark.parametrize("reconnect_timeout", [60.0, 0.3])
def test_a_fresh_session_after_a_server_restart(avatar, reconnect_timeout):
    """The server goes away mid-stream and comes back on the same port knowing no session: every
    frame sent meanwhile still comes out (unstyled, promptly), then a fresh session restyles:
    the SDK's own (it reconnects for `reconnect_timeout`), or, once the SDK has given up, the
    bridge's."""
    import time

    from clients.loadtest import free_port

    port = free_port()
    source = Sender(avatar)
    models = {"lti": _lti()}
    first = _server_on(port, models)
    url = first.__enter__()
    try:
        with _bridge(url, reconnect_timeout) as (bridge, sender, sink):
            _stream_styled(bridge, sender, sink, source, frames=5)
            first.__exit__(None, None, None)
            first = None
            slowest = 0.0
            t = 0
            while t < 20 or (reconnect_timeout < 1 and bridge.link.failures == 0):  # down: frames come out unstyled
                t0 = time.perf_counter()
                bones, _ = _parse(_round(bridge, sender, sink, source.bundle(t % FRAMES)))
                slowest = max(slowest, time.perf_counter() - t0)
                assert set(bones) == set(source.names)
                t += 1
                assert t < 20000, "the SDK session never gave up"
            with _server_on(port, models):
                sent, styled = 0, bridge.stats.styled
                while bridge.stats.styled == styled:  # a fresh session (the SDK's or the bridge's) restyles
                    _round(bridge, sender, sink, source.bundle(sent % FRAMES))
                    sent += 1
                    assert sent < 5000, "no fresh session"
                frames = _stream_styled(bridge, sender, sink, source, frames=5)
            assert len(frames) == 5
            assert slowest < 2.0, slowest  # a frame waits at most for --wait-ms, not for the reconnects
    finally:
        if first is not None:
            first.__exit__(None, None, None)
