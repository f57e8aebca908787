"""VMC bridge: the pure BN <-> VMC mapping, and end to end over real OSC/UDP on loopback."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from clients.vmc import (BN_TO_UNITY, TPOSE_DIRECTIONS, VmcBridge, VmcFrame, VmcReceiver, bn_to_vmc, build_bundle,
                         default_vmc_rig, parse_vmc_messages, right_handed_to_unity, session_stylise,
                         unity_to_right_handed, vmc_messages, vmc_to_bn)
from models.motion.rotations import quat_apply
from models.motion.skeleton import fk


@pytest.fixture(scope="module")
def walk():
    from models.data import build_index, load_motion, select

    clip = select(build_index(["bandai-namco-2"]), style="normal", content="walk", split="val")[0]
    m = load_motion(clip)
    rotations = m.rotations.astype(np.float64)
    rotations /= np.linalg.norm(rotations, axis=-1, keepdims=True)
    return m.translations[:, m.skeleton.index("Hips")].astype(np.float64), rotations


def _same_quats(a: np.ndarray, b: np.ndarray) -> float:
    """Largest difference, q and -q being one rotation."""
    sign = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -1.0, 1.0)
    return float(np.abs(a - sign * b).max())


def test_handedness_is_an_involution():
    rng = np.random.default_rng(0)
    p, q = rng.normal(size=(5, 3)), rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    p2, q2 = unity_to_right_handed(p, q)
    assert np.allclose(p2, p * [-1, 1, 1]) and np.allclose(q2, q * [1, -1, -1, 1])
    back = right_handed_to_unity(p2, q2)
    assert np.allclose(back[0], p) and np.allclose(back[1], q)
    # the mirror is a homomorphism: mirrored rotation applied to mirrored vector = mirrored result
    v = rng.normal(size=(5, 3))
    assert np.allclose(quat_apply(q2, v * [-1, 1, 1]), quat_apply(q, v) * [-1, 1, 1])


def test_round_trip_on_real_walk(walk):
    roots, rotations = walk
    rig = default_vmc_rig()
    for i in range(0, len(roots), 5):
        frame = bn_to_vmc(roots[i], rotations[i], rig)
        assert set(frame.bones) == set(BN_TO_UNITY.values())
        parsed = parse_vmc_messages(vmc_messages(frame, t=i / 30))
        root, rot = vmc_to_bn(parsed, rig)
        assert np.abs(root - roots[i]).max() < 1e-6
        assert np.abs(rot - rotations[i]).max() < 1e-6


def test_tpose_maps_to_bone_directions():
    rig = default_vmc_rig()
    sk = rig.skeleton
    root, rot = vmc_to_bn(VmcFrame(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])), rig)
    translations = np.array(sk.offsets)
    translations[sk.index("Hips")] = root
    _, pos = fk(rot, translations, sk.parents)
    checked = 0
    for parent, child in (("Hips", "Spine"), ("Spine", "Chest"), ("Chest", "Neck"), ("Neck", "Head"),
                          *((f"{a}_{s}", f"{b}_{s}") for s in "LR" for a, b in (
                              ("Shoulder", "UpperArm"), ("UpperArm", "LowerArm"), ("LowerArm", "Hand"),
                              ("UpperLeg", "LowerLeg"), ("LowerLeg", "Foot")))):
        d = pos[sk.index(child)] - pos[sk.index(parent)]
        assert np.allclose(d / np.linalg.norm(d), TPOSE_DIRECTIONS[parent], atol=1e-6), parent
        checked += 1
    assert checked == 14
    # hip and shoulder lines along +X (left at +X), feet point forward (+Z), symmetric
    for a, b in (("UpperLeg_L", "UpperLeg_R"), ("Shoulder_L", "Shoulder_R")):
        d = pos[sk.index(a)] - pos[sk.index(b)]
        assert np.allclose(d / np.linalg.norm(d), [1, 0, 0], atol=1e-4)  # BN offsets: L/R differ by 3e-4 cm
    for s in "LR":
        d = pos[sk.index(f"Toes_{s}")] - pos[sk.index(f"Foot_{s}")]
        assert abs(d[0]) < 1e-6 and d[2] > 0 and d[1] < 0
    # and back: a T-pose BN frame gives identity VMC rotations
    frame = bn_to_vmc(root, rot, rig)
    for name, (_, q) in frame.bones.items():
        assert _same_quats(q, np.array([0.0, 0.0, 0.0, 1.0])) < 1e-9, name


def test_loose_messages_complete_on_time():
    frames = []
    receiver = VmcReceiver(lambda f, m: frames.append(f))
    from pythonosc.osc_message_builder import OscMessageBuilder

    frame = bn_to_vmc(np.array([0.0, 90.0, 0.0]), np.tile([0.0, 0.0, 0.0, 1.0], (22, 1)))
    for address, args in vmc_messages(frame, t=1.0):
        msg = OscMessageBuilder(address=address)
        for a in args:
            msg.add_arg(a)
        receiver.dispatcher.call_handlers_for_packet(msg.build().dgram, ("127.0.0.1", 0))
    assert len(frames) == 1 and set(frames[0].bones) == set(BN_TO_UNITY.values())
    receiver.dispatcher.call_handlers_for_packet(build_bundle(vmc_messages(frame)).dgram, ("127.0.0.1", 0))
    assert len(frames) == 2


def test_bridge_end_to_end_over_udp(walk):
    from pythonosc import osc_server, udp_client

    from clients.sdk import Client
    from models.registry import load_models
    from models.settings import get_settings

    from .live_server import live_server

    roots, rotations = walk[0][:30], walk[1][:30]
    rig = default_vmc_rig()
    received: list[tuple[VmcFrame, list]] = []
    got_all = threading.Event()

    def on_frame(frame, messages):
        received.append((frame, messages))
        if len(received) >= 30:
            got_all.set()

    out_receiver = VmcReceiver(on_frame)
    sink = osc_server.BlockingOSCUDPServer(("127.0.0.1", 0), out_receiver.dispatcher)
    sink_thread = threading.Thread(target=sink.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    sink_thread.start()
    with live_server(load_models(get_settings().weights_dir)) as (url, _):
        client = Client(url)
        with client.session(model="lti", style="elderly") as session:
            bridge = VmcBridge(session_stylise(session), "127.0.0.1", sink.server_address[1], "127.0.0.1", 0, rig)
            thread = bridge.start()
            try:
                sender = udp_client.SimpleUDPClient("127.0.0.1", bridge.address[1])
                for i in range(30):
                    sender.send(build_bundle(vmc_messages(bn_to_vmc(roots[i], rotations[i], rig), t=i / 30)))
                    time.sleep(0.002)
                assert got_all.wait(30), f"only {len(received)} of 30 frames came back"
            finally:
                bridge.shutdown()
                thread.join(5)
        with client.session(model="lti", style="elderly") as direct:
            expected = [direct.stylise(roots[i], rotations[i]) for i in range(30)]
    sink.shutdown()
    sink.server_close()

    assert len(received) == 30 and bridge.frames == 30 and bridge.errors == 0
    names = set(BN_TO_UNITY.values())
    for (frame, messages), want in zip(received, expected):
        bones = [args[0] for address, args in messages if address == "/VMC/Ext/Bone/Pos"]
        assert set(bones) == names and len(bones) == len(names)
        assert [args[0] for address, args in messages if address == "/VMC/Ext/Root/Pos"] == ["root"]
        assert any(address == "/VMC/Ext/T" for address, _ in messages)
        root, rot = vmc_to_bn(frame, rig)
        assert np.abs(root - want.root).max() < 1e-3  # cm; OSC carries metres as float32
        assert _same_quats(rot, want.rotations) < 1e-4
    # the stylised walk is not the input walk
    assert max(_same_quats(vmc_to_bn(f, rig)[1], rotations[i]) for i, (f, _) in enumerate(received)) > 1e-3
