"""What the VMC bridge adds to a frame, end to end with a VMC sender:

    python -m clients.vmc bench [--url http://127.0.0.1:8000] [--frames 600] [--fps 60] [--model lti]

A VMC sender (this process) sends a real walk as a VSeeFace-like avatar would: 55 Unity bones
(body, fingers, eyes, jaw; a Bandai Namco walk put on the Unity humanoid preset by the humanoid
mapping, metres, Unity axes) plus blend shapes, OK and T, one bundle per frame at `--fps`, and
waits for each frame to come back from the bridge (a `stylestream vmc` process) before the next
tick. The same frames also go straight to the server through an SDK session on the same avatar
rig. Both in turns (direct, bridge, direct, bridge) against one server (started here unless
`--url`). The bridge's cost is the end-to-end median minus the direct one; the bridge also reports
its own time per frame (decode, convert, encode; the session wait excluded).
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import subprocess
import sys
import time
from contextlib import ExitStack

import numpy as np

from . import vmc_osc as osc
from .vmc import BONE_ADDRESS, ROOT_ADDRESS, VmcState, avatar_rig, model_input

BLEND = [("/VMC/Ext/Blend/Val", [name, 0.0]) for name in ("A", "I", "U", "E", "O", "Blink_L", "Blink_R", "Joy")] + [
    ("/VMC/Ext/Blend/Apply", [])
]
EXTRA_BONES = {"LeftEye": (0.03, 0.07, 0.08), "RightEye": (-0.03, 0.07, 0.08), "Jaw": (0.0, 0.0, 0.05)}


def sender_frames(n: int, fps: float) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(bone names, local positions (n, B, 3), rotations (n, B, 4)) of a real walk on a Unity
    humanoid avatar, in VMC's Unity axes and metres."""
    from models.motion.humanoid import preset_rig
    from models.motion.retarget_stream import FrameRetargeter

    from .loadtest import real_frames

    root, rot = real_frames(n, fps)  # the walk at its own speed at `fps`
    rig = preset_rig("unity")
    sk = rig.skeleton
    rest = np.tile([0.0, 0.0, 0.0, 1.0], (n, sk.num_joints, 1))
    hips, local = FrameRetargeter(rig).to_source(root.astype(np.float64), rot.astype(np.float64), rest)
    names = list(sk.names) + list(EXTRA_BONES)
    pos = np.concatenate(
        [
            np.broadcast_to(sk.offsets, (n, sk.num_joints, 3)).copy(),
            np.broadcast_to(np.array(list(EXTRA_BONES.values())) * 100, (n, len(EXTRA_BONES), 3)),
        ],
        axis=1,
    )
    pos[:, sk.index("Hips")] = hips
    rot = np.concatenate([local, np.tile([0.0, 0.0, 0.0, 1.0], (n, len(EXTRA_BONES), 1))], axis=1)
    return names, pos / 100.0 * [-1.0, 1.0, 1.0], rot * [1.0, -1.0, -1.0, 1.0]  # cm -> m, mirrored to Unity


def bundles(names: list[str], pos: np.ndarray, rot: np.ndarray, fps: float) -> list[bytes]:
    """One VMC bundle per frame."""
    enc = osc.PoseEncoder(BONE_ADDRESS)
    root = osc.element(osc.encode_message(ROOT_ADDRESS, ["root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    blend = [osc.element(osc.encode_message(a, args)) for a, args in BLEND]
    ok = osc.element(osc.encode_message("/VMC/Ext/OK", [1]))
    out = []
    for t in range(len(pos)):
        bones = enc.elements(names, np.concatenate([pos[t], rot[t]], axis=1))
        out += osc.bundles([root, *bones, *blend, ok, osc.element(osc.encode_message("/VMC/Ext/T", [t / fps]))])
    return out


def _pace(t0: float, i: int, fps: float) -> None:
    wait = t0 + i / fps - time.perf_counter()
    if wait > 0:
        time.sleep(wait)


def _arm(datagram: bytes) -> np.ndarray | None:
    """LeftUpperArm's rotation in a bridge output (to tell restyled frames from passed-through ones)."""
    for m in osc.elements(datagram):
        if osc.address(m) == BONE_ADDRESS.encode():
            pose = osc.decode_pose(m)
            if pose is not None and pose[0] == "LeftUpperArm":
                return np.array(pose[1][3:])
    return None


def measure_bridge(port: int, sink: socket.socket, data: list[bytes], fps: float) -> list[float]:
    """Per-frame latency (s) from sending a frame to the bridge's bundle for it coming back."""
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    lat = []
    t0 = time.perf_counter()
    for i, d in enumerate(data):
        _pace(t0, i, fps)
        start = time.perf_counter()
        out.sendto(d, ("127.0.0.1", port))
        sink.recv(65536)
        lat.append(time.perf_counter() - start)
    out.close()
    return lat


def measure_direct(session, inputs: list[tuple[np.ndarray, np.ndarray]], fps: float) -> list[float]:
    lat = []
    t0 = time.perf_counter()
    for i, (root, rot) in enumerate(inputs):
        _pace(t0, i, fps)
        start = time.perf_counter()
        session.stylise(root, rot)
        lat.append(time.perf_counter() - start)
    return lat


def _stats(a: list[float]) -> str:
    ms = np.array(a) * 1e3
    return f"median {np.median(ms):6.3f}  p90 {np.percentile(ms, 90):6.3f}  p99 {np.percentile(ms, 99):6.3f}"


def main(argv: list[str]) -> int:
    from .sdk import Client

    p = argparse.ArgumentParser(prog="python -m clients.vmc bench")
    p.add_argument("--url", help="a running server (default: start one here)")
    p.add_argument("--model", default="lti")
    p.add_argument("--style", default="elderly")
    p.add_argument("--frames", type=int, default=600, help="measured frames per path (two turns of half)")
    p.add_argument("--fps", type=float, default=60.0)
    args = p.parse_args(argv)
    names, pos, rot = sender_frames(args.frames + 60, args.fps)
    data = bundles(names, pos, rot, args.fps)
    arm_in = rot[:, names.index("LeftUpperArm")]
    # the model input the bridge makes of each frame, for the direct path
    state = VmcState()
    state.update(names, np.concatenate([pos[0], rot[0]], axis=1), 0.0)
    rig = avatar_rig(state.body())
    slots = np.array([state.slot[b] for b in rig.bones])
    inputs = []
    for t in range(len(pos)):
        state.update(names, np.concatenate([pos[t], rot[t]], axis=1), 0.0)
        inputs.append(model_input(slots, state))

    with ExitStack() as stack:
        url = args.url
        if url is None:
            from .loadtest import spawned_server

            ws, _ = stack.enter_context(spawned_server())
            url = ws.replace("ws://", "http://").rsplit("/v1/", 1)[0]
        sink = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        sink.bind(("127.0.0.1", 0))
        sink.settimeout(10)
        listen = _free_udp_port()
        bridge = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "clients.vmc",
                "--listen",
                str(listen),
                "--send-port",
                str(sink.getsockname()[1]),
                "--url",
                url,
                "--model",
                args.model,
                "--style",
                args.style,
                "--fps",
                str(min(args.fps, 240.0)),
                "--stats",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        stack.callback(_stop, bridge)
        assert bridge.stdout is not None
        print(bridge.stdout.readline().strip())
        # warm up: until the bridge's session restyles (opening it, the first steps)
        warm = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        deadline = time.monotonic() + 60
        warm_frames = 0
        while True:
            warm_frames += 1
            warm.sendto(data[0], ("127.0.0.1", listen))
            arm = _arm(sink.recv(65536))
            if arm is not None and not np.allclose(arm, np.float32(arm_in[0]), atol=1e-7):
                break
            if time.monotonic() > deadline:
                raise RuntimeError("the bridge never restyled a frame")
        warm.close()
        client = stack.enter_context(Client(url))
        session = stack.enter_context(
            client.session(
                model=args.model, style=args.style, skeleton=None, bvh_header=rig.header, fps=min(args.fps, 240.0)
            )
        )
        measure_direct(session, inputs[:60], args.fps)  # warm up
        half = args.frames // 2
        direct, through = [], []
        for k in range(2):
            part = slice(60 + k * half, 60 + (k + 1) * half)
            direct += measure_direct(session, inputs[part], args.fps)
            through += measure_bridge(listen, sink, data[part], args.fps)
        bridge.send_signal(signal.SIGINT)
        out, _ = bridge.communicate(timeout=30)
        summary = json.loads(out.strip().splitlines()[-1])
    unstyled = summary["frames"] - warm_frames - (summary["styled"] - 1)  # measured frames the bridge passed through
    added = (np.median(through) - np.median(direct)) * 1e3
    print(
        f"VMC frames of {len(names)} bones + {len(BLEND)} blend shape messages, {args.frames} per path at {args.fps:g} fps, "
        f"{args.model}/{args.style}"
    )
    print(f"direct SDK session round trip  (ms): {_stats(direct)}")
    print(
        f"sender -> bridge -> server -> bridge -> receiver (ms): {_stats(through)}  ({unstyled} passed through unstyled)"
    )
    print(f"added by the bridge at the median: {added:.3f} ms")
    print(
        f"bridge's own time per frame (decode, convert, encode; the session wait apart): median "
        f"{summary['bridge_us_median']} us, p99 {summary['bridge_us_p99']} us; waiting on its session: median "
        f"{summary['session_us_median']} us"
    )
    return 0


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.kill()
        process.wait()


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
