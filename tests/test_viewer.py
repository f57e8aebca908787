"""The browser viewer against a real server: the page and its files are served, the demo clip is
valid, and headless Chromium (when /usr/bin/chromium exists) renders two streamed skeletons:
once with the `--screenshot` command line, once over the DevTools protocol in real time, where
the page's own counters say it streamed at the clip's frame rate with a sane round trip."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from models.motion.assets import bandai_namco_skeleton
from models.registry import load_models
from models.settings import get_settings
from service.viewer import DemoClip, rocking_pose
from clients.loadtest import free_port
from tests.live_server import live_server

CHROMIUM = Path("/usr/bin/chromium")
OUT = Path(__file__).resolve().parents[1] / "out"  # git-ignored: screenshots to look at
# WebGL without a GPU: ANGLE on SwiftShader (software), which Chromium only uses when told to
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--window-size=1000,600"]
# the skeleton colours of viewer.js (left limbs): input blue, stylised orange
INPUT_RGB, OUTPUT_RGB = (0x4E, 0xA1, 0xFF), (0xFF, 0x8A, 0x3D)


@pytest.fixture(scope="module")
def server():
    with live_server(load_models(get_settings().weights_dir)) as (base, _app):
        yield base


def need_chromium() -> None:
    if not CHROMIUM.exists():
        reason = f"{CHROMIUM} is absent (apt-get install -y chromium): the viewer is not rendered in a browser"
        print(reason)
        pytest.skip(reason)


def colour_pixels(img: Image.Image, rgb: tuple[int, int, int], tol: int = 40) -> np.ndarray:
    a = np.asarray(img.convert("RGB")).astype(int)
    return np.all(np.abs(a - np.array(rgb)) <= tol, axis=-1)


def check_two_skeletons(png: Path) -> None:
    img = Image.open(png).convert("RGB")
    w, h = img.size
    assert (w, h) == (1000, 600)
    a = np.asarray(img).astype(float)
    assert a.std() > 10, f"screenshot {png} is blank (pixel std {a.std():.1f})"
    canvas = slice(int(0.25 * h), int(0.85 * h))  # below the controls and panel titles, above the HUD
    for name, rgb, cols in (("input", INPUT_RGB, slice(0, w // 2)), ("stylised", OUTPUT_RGB, slice(w // 2, w))):
        mask = colour_pixels(img, rgb)[canvas, cols]
        ys, xs = np.nonzero(mask)
        assert len(ys) > 300, f"no {name} skeleton drawn in {png} ({len(ys)} pixels of its colour)"
        tall, wide = np.ptp(ys), np.ptp(xs)
        assert tall > 1.5 * wide and tall > 0.3 * h, f"{name} skeleton is not upright: {tall} px tall, {wide} px wide"
    # and nothing of the stylised colour on the input side, or the other way round (side by side)
    assert colour_pixels(img, OUTPUT_RGB)[canvas, : w // 2].sum() < 50
    assert colour_pixels(img, INPUT_RGB)[canvas, w // 2:].sum() < 50


def test_viewer_page_and_static_files(server):
    page = httpx.get(f"{server}/viewer")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "/viewer/static/viewer.js" in page.text and '<canvas id="view">' in page.text
    js = httpx.get(f"{server}/viewer/static/viewer.js")
    assert js.status_code == 200 and "javascript" in js.headers["content-type"] and "/v1/stream" in js.text
    assert httpx.get(f"{server}/viewer/static/viewer.css").headers["content-type"].startswith("text/css")
    for bad in ("nope.js", "..%2Fviewer.py", "..%2F..%2Fservice%2Fapp.py", "demo_walk.bvh"):
        assert httpx.get(f"{server}/viewer/static/{bad}").status_code == 404


def check_clip(clip: dict) -> None:
    DemoClip.model_validate(clip)
    sk = bandai_namco_skeleton()
    assert clip["joints"] == list(sk.names)
    assert clip["parents"] == [int(p) for p in sk.parents]
    assert np.allclose(clip["offsets"], sk.offsets, atol=1e-3)
    assert clip["joints"][clip["root_joint"]] == "Hips"
    root = np.array(clip["frames"]["root"])
    rot = np.array(clip["frames"]["rotations"])
    assert 90 <= len(root) <= 180 and clip["fps"] == 30  # 3-6 seconds
    assert root.shape == (len(root), 3) and rot.shape == (len(root), len(sk.names), 4)
    assert np.all(np.isfinite(root)) and np.allclose(np.linalg.norm(rot, axis=-1), 1, atol=1e-3)
    assert np.all((70 < root[:, 1]) & (root[:, 1] < 110)), "Hips height in cm, Y up"


def test_demo_clip_is_a_walk(server):
    r = httpx.get(f"{server}/v1/demo/clip")
    assert r.status_code == 200
    clip = r.json()
    check_clip(clip)
    root = np.array(clip["frames"]["root"])
    speed = np.linalg.norm(root[-1, [0, 2]] - root[0, [0, 2]]) / (len(root) / clip["fps"])
    assert 60 < speed < 200, f"a walk covers 0.6-2 m/s, this one {speed:.0f} cm/s"
    # the frames stream as they are: the server stylises every one
    from clients.sdk import Client
    with Client(server).session(model="lti", style="elderly") as s:
        for root_t, rot_t in list(zip(clip["frames"]["root"], clip["frames"]["rotations"]))[:10]:
            out = s.stylise(np.array(root_t), np.array(rot_t))
            assert np.all(np.isfinite(out.rotations))


def test_rocking_pose_fallback_is_valid():
    clip = rocking_pose()
    check_clip(json.loads(json.dumps(clip)))
    rot = np.array(clip["frames"]["rotations"])
    assert np.abs(np.diff(rot, axis=0)).max() > 1e-3  # it moves


def test_viewer_screenshot_in_headless_chromium(server, tmp_path):
    need_chromium()
    png = tmp_path / "viewer.png"
    cmd = [str(CHROMIUM), *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=5000",
           f"--screenshot={png}", f"{server}/viewer?autoplay=1"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert png.exists(), f"chromium wrote no screenshot (rc {proc.returncode}): {proc.stderr[-2000:]}"
    keep = OUT / "viewer_test.png"
    keep.parent.mkdir(exist_ok=True)
    shutil.copy(png, keep)  # out/ is git-ignored: a copy to look at
    check_two_skeletons(png)


def test_viewer_streams_in_real_time(server, tmp_path):
    """Chromium driven over the DevTools protocol with real time running: the page streams the
    demo clip at 30 fps, every frame comes back, the readout shows the round trip, and a style
    switch with a transition is acknowledged."""
    need_chromium()
    from websockets.sync.client import connect

    port = free_port()
    proc = subprocess.Popen([str(CHROMIUM), *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}",
                             f"--remote-debugging-port={port}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                targets = httpx.get(f"http://127.0.0.1:{port}/json/list", timeout=1).json()
                page = next(t for t in targets if t.get("type") == "page")
                break
            except (httpx.TransportError, StopIteration, ValueError):
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("chromium's DevTools endpoint did not come up") from None
                time.sleep(0.1)
        with connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as cdp:
            ids = iter(range(1, 10**6))

            def call(method: str, **params) -> dict:
                i = next(ids)
                cdp.send(json.dumps({"id": i, "method": method, "params": params}))
                while True:
                    m = json.loads(cdp.recv(timeout=30))
                    if m.get("id") == i:
                        assert "error" not in m, m
                        return m["result"]

            def js(expr: str):
                return call("Runtime.evaluate", expression=expr, returnByValue=True)["result"].get("value")

            call("Emulation.setDeviceMetricsOverride", width=1000, height=600, deviceScaleFactor=1, mobile=False)
            call("Page.navigate", url=f"{server}/viewer?autoplay=1&model=lti&style=elderly")
            deadline = time.monotonic() + 20
            while js("document.body && document.body.dataset.state") != "streaming" or int(js("document.body.dataset.received") or 0) < 5:
                status = js("document.getElementById('status').textContent")
                assert time.monotonic() < deadline, f"viewer did not stream: state {js('document.body.dataset.state')!r}, {status!r}"
                time.sleep(0.1)
            t0, n0 = time.monotonic(), int(js("document.body.dataset.received"))
            time.sleep(3.0)
            js("document.getElementById('style').value = 'exhausted';"
               "document.getElementById('style').dispatchEvent(new Event('change'))")
            time.sleep(1.0)
            rate = (int(js("document.body.dataset.received")) - n0) / (time.monotonic() - t0)
            hud = js("document.getElementById('hud').innerText")
            print(f"viewer in real time: {rate:.1f} frames/s received; HUD: {hud!r}")
            assert rate > 10, f"expected a live stream (~30 frames/s), got {rate:.1f}"  # speed is benchmarked elsewhere
            mean = float(js("document.getElementById('lat-mean').textContent"))
            assert 0 < mean < 2000, f"mean round trip {mean} ms"
            assert "dropped 0" in hud
            assert "exhausted 1.00" in hud, hud  # the style_set reply's weights
            shot = call("Page.captureScreenshot", format="png")["data"]
        png = tmp_path / "viewer_live.png"
        png.write_bytes(base64.b64decode(shot))
        OUT.mkdir(exist_ok=True)
        shutil.copy(png, OUT / "viewer_live.png")
        check_two_skeletons(png)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
