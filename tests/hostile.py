"""A healthy session streaming beside hostile clients: it must get every frame back, exactly the
output of the model stepped offline, however the others behave; and the uploads they send."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
from websockets.sync.client import connect

from clients.hostile_bench import looped_bvh
from models.interface import StreamingModel
from models.motion.skeleton import Motion

from .live_server import offline, ws_url
from .waiting import wait_until


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
        """Starts streaming and returns once the first frame is back (or the session failed), so
        whatever the test does next happens while this session streams."""
        self._thread.start()
        wait_until(lambda: self.outputs or self.errors, "the healthy session's first frame", timeout=60)
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
        _, want = offline(model, {self.style: 1.0}, self.root[idx], self.rot[idx])
        np.testing.assert_allclose(np.array(self.outputs), want, atol=1e-9)

    def p99_ms(self, since: int = 0) -> float:
        return float(np.percentile(np.array(self.rtts[since:]) * 1000, 99))


def json_clip(name: str, walk, fps: float, model: str = "lpn") -> dict:
    return {
        "name": name,
        "model": model,
        "fps": fps,
        "frames": {"root": walk.translations[:, 1].tolist(), "rotations": walk.rotations.tolist()},
    }


def longest_bvh(walk, frames: int = 9000) -> str:
    """A BVH of `frames` at 30 fps (default: the longest clip accepted) looping `walk`'s rows."""
    return looped_bvh(walk, frames)
