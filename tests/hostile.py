"""A healthy session streaming beside hostile clients: it must get every frame back, exactly the
output of the model stepped offline, however the others behave."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import threading
import time

import numpy as np
from websockets.sync.client import connect

from models.interface import FrameBatch, StreamingModel, style_vector
from models.motion.skeleton import Motion


def ws_url(base: str) -> str:
    return base.replace("http", "ws") + "/v1/stream"


def offline(model: StreamingModel, style: str, root: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """The model stepped frame by frame in process: what a session must stream back."""
    state, w, out = model.init_state(1), style_vector(model, {style: 1.0})[None], []
    for t in range(len(root)):
        fb, state = model.step_batch(state, FrameBatch(root[t : t + 1], rot[t : t + 1]), w)
        out.append(fb.rotations[0])
    return np.array(out)


class Bystander:
    """Streams `walk` (looped) to `model`/`style` at up to `fps`, one frame in flight, in a thread;
    keeps every reply's rotations and round-trip time. `check` compares with `offline`."""

    def __init__(self, base: str, walk: Motion, model: str = "lti", style: str = "elderly", fps: float = 60.0) -> None:
        self.base, self.model, self.style, self.fps = base, model, style, fps
        self.root, self.rot = walk.translations[:, 1].copy(), walk.rotations.copy()
        self.outputs: list[list] = []
        self.rtts: list[float] = []
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Bystander:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=60)

    def _run(self) -> None:
        try:
            with connect(ws_url(self.base)) as ws:
                ws.send(json.dumps({"type": "start", "model": self.model, "style": self.style}))
                assert json.loads(ws.recv(timeout=30))["type"] == "started"
                t = 0
                while not self._stop.is_set():
                    k = t % len(self.root)
                    sent = time.perf_counter()
                    frame = {
                        "type": "frame",
                        "seq": t,
                        "root": self.root[k].tolist(),
                        "rotations": self.rot[k].tolist(),
                    }
                    ws.send(json.dumps(frame))
                    reply = json.loads(ws.recv(timeout=30))
                    if reply.get("type") != "frame" or reply.get("seq") != t:
                        self.errors.append(f"frame {t}: {reply}")
                        return
                    self.rtts.append(time.perf_counter() - sent)
                    self.outputs.append(reply["rotations"])
                    t += 1
                    time.sleep(max(0.0, 1 / self.fps - (time.perf_counter() - sent)))
        except Exception as exc:  # noqa: BLE001  (reported by `check`)
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def frames(self) -> int:
        return len(self.outputs)

    def check(self, model: StreamingModel) -> None:
        """Every frame came back, and each is exactly the offline model's output."""
        assert not self.errors, self.errors
        n = len(self.outputs)
        assert n > 0, "the healthy session got no frames back"
        idx = np.arange(n) % len(self.root)
        want = offline(model, self.style, self.root[idx], self.rot[idx])
        np.testing.assert_allclose(np.array(self.outputs), want, atol=1e-9)

    def p99_ms(self, since: int = 0) -> float:
        return float(np.percentile(np.array(self.rtts[since:]) * 1000, 99))


class RawSocket:
    """A bare TCP connection to the server, with a small receive buffer so replies back up."""

    def __init__(self, base: str, rcvbuf: int = 4096) -> None:
        host, port = base.split("//")[1].split(":")
        self.host, self.port = host, int(port)
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.connect((self.host, self.port))

    def closed_by_server(self, timeout: float) -> bool:
        """Read (and discard) until the server drops the connection; False if it has not within
        `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                if not self.sock.recv(65536):
                    return True
            except TimeoutError:
                return False
            except OSError:  # reset: the server aborted
                return True
        return False

    def close(self) -> None:
        self.sock.close()


class RawClient(RawSocket):
    """A WebSocket client that reads only when told to (a browser tab gone to sleep, a stalled
    game thread): the handshake by hand, then masked text frames."""

    def __init__(self, base: str, rcvbuf: int = 4096) -> None:
        super().__init__(base, rcvbuf)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET /v1/stream HTTP/1.1\r\nHost: {self.host}:{self.port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            assert chunk, "connection closed during the handshake"
            head += chunk
        assert head.startswith(b"HTTP/1.1 101"), head

    def send_text(self, text: str) -> None:
        """One masked text frame (RFC 6455: clients mask)."""
        payload = text.encode()
        n = len(payload)
        if n < 126:
            length = bytes([0x80 | n])
        elif n < 65536:
            length = bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            length = bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        masked = (np.frombuffer(payload, np.uint8) ^ np.resize(np.frombuffer(mask, np.uint8), n)).tobytes()
        self.sock.sendall(bytes([0x81]) + length + mask + masked)
