"""The browser viewer against a real server: the page, its modules and the vendored three.js are
served, the demo clip is valid, and headless Chromium (when /usr/bin/chromium exists) draws two
streamed 3-D skeletons with WebGL: once with the `--screenshot` command line, once over the
DevTools protocol in real time, where the page's own counters say it streamed at the clip's frame
rate, the style triangle's point sets a 3-way mix on the server, held keys and a gamepad
become the LPN controller's `control` messages, and held keys walk, turn and stop the committed
LPN-FiLM character through the server."""

from __future__ import annotations

import base64
import json
import math
import re
import shutil
import subprocess
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from clients.loadtest import free_port
from models.data import build_index, select
from models.motion.assets import bandai_namco_skeleton
from models.registry import load_models
from models.settings import get_settings
from service.viewer import VIEWER_DIR, DemoClip, rocking_pose
from tests.live_server import live_server
from tests.waiting import wait_until

CHROMIUM = Path("/usr/bin/chromium")
OUT = Path(__file__).resolve().parents[1] / "out"  # git-ignored: screenshots to look at
# WebGL without a GPU: ANGLE on SwiftShader (software), which Chromium only uses when told to
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=1000,600",
]
# the skeleton colours of scene.js (left limbs): input blue, stylised orange
INPUT_RGB, OUTPUT_RGB = (0x4E, 0xA1, 0xFF), (0xFF, 0x8A, 0x3D)
THREE_DIR = VIEWER_DIR / "vendor" / "three"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    styles = tmp_path_factory.mktemp("styles")  # where a dropped clip's style goes
    with live_server(load_models(get_settings().weights_dir), styles_dir=styles) as (base, _app):
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
    assert colour_pixels(img, INPUT_RGB)[canvas, w // 2 :].sum() < 50


def test_viewer_page_modules_and_vendored_three_are_served(server):
    page = httpx.get(f"{server}/viewer")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "/viewer/static/viewer.js" in page.text and '<canvas id="view">' in page.text
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', page.text, re.S).group(1))["imports"]
    for module in (
        "viewer.js",
        "kinematics.js",
        "scene.js",
        "triangle.js",
        "controller.js",
        "vendor/three/three.module.min.js",
        "vendor/three/three.core.min.js",
        "vendor/three/addons/controls/OrbitControls.js",
    ):
        r = httpx.get(f"{server}/viewer/static/{module}")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/javascript"), module  # ES modules
    assert all(path.startswith("/viewer/static/vendor/") for path in imports.values())  # served here, no CDN
    assert httpx.get(f"{server}{imports['three']}").status_code == 200
    assert httpx.get(f"{server}{imports['three/addons/']}controls/OrbitControls.js").status_code == 200
    assert "/v1/stream" in httpx.get(f"{server}/viewer/static/viewer.js").text
    assert httpx.get(f"{server}/viewer/static/viewer.css").headers["content-type"].startswith("text/css")
    for bad in (
        "nope.js",
        "..%2Fviewer.py",
        "..%2F..%2Fservice%2Fapp.py",
        "demo_walk.bvh",
        "vendor/three/VERSION",
        "vendor/fetch-three.sh",
        "vendor/three/..%2F..%2F..%2F..%2Fservice%2Fviewer.py",
    ):
        assert httpx.get(f"{server}/viewer/static/{bad}").status_code == 404, bad


def test_vendored_three_is_one_recorded_npm_release():
    """The vendored files are the npm release VERSION names (its revision is in the code), small
    enough to commit, with the MIT licence; nothing refers to a CDN."""
    info = (THREE_DIR / "VERSION").read_text()
    version = re.match(r"three@(0\.(\d+)\.\d+) from the npm registry", info)
    assert version, info
    assert re.search(r"integrity sha512-[A-Za-z0-9+/]{86}==", info)
    assert f'="{version.group(2)}"' in (THREE_DIR / "three.core.min.js").read_text()  # REVISION
    assert "MIT License" in (THREE_DIR / "LICENSE").read_text()
    size = sum(f.stat().st_size for f in THREE_DIR.rglob("*") if f.is_file())
    assert size < 1.5e6, f"vendored three.js is {size / 1e6:.2f} MB"
    for f in VIEWER_DIR.glob("*.*"):
        if f.suffix in (".js", ".html", ".css"):
            assert not re.search(r"https?://(?!www\.w3\.org/2000/svg)", f.read_text()), (
                f"{f.name} loads something from the web"
            )


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
    cmd = [
        str(CHROMIUM),
        *CHROMIUM_FLAGS,
        f"--user-data-dir={tmp_path / 'profile'}",
        "--virtual-time-budget=5000",
        f"--screenshot={png}",
        f"{server}/viewer?autoplay=1",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert png.exists(), f"chromium wrote no screenshot (rc {proc.returncode}): {proc.stderr[-2000:]}"
    keep = OUT / "viewer_test.png"
    keep.parent.mkdir(exist_ok=True)
    shutil.copy(png, keep)  # out/ is git-ignored: a copy to look at
    check_two_skeletons(png)


class DevTools:
    """A page of a headless Chromium, driven over the DevTools protocol."""

    def __init__(self, cdp):
        self.cdp = cdp
        self.ids = iter(range(1, 10**6))
        self.handlers: dict[str, Callable[[dict], None]] = {}  # event method -> handler(params)

    def call(self, method: str, **params) -> dict:
        i = next(self.ids)
        self.cdp.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            m = json.loads(self.cdp.recv(timeout=30))
            if m.get("id") == i:
                assert "error" not in m, m
                return m["result"]
            if m.get("method") in self.handlers:
                self.handlers[m["method"]](m["params"])

    def send(self, method: str, **params) -> None:
        """A command whose answer nobody waits for (from inside an event handler)."""
        self.cdp.send(json.dumps({"id": next(self.ids), "method": method, "params": params}))

    def js(self, expr: str):
        """The value of a JavaScript expression (awaited when it is a promise); page errors fail the test."""
        r = self.call("Runtime.evaluate", expression=expr, returnByValue=True, awaitPromise=True)
        assert "exceptionDetails" not in r, r["exceptionDetails"]
        return r["result"].get("value")

    def key(self, kind: str, code: str, key: str, vk: int) -> None:
        self.call("Input.dispatchKeyEvent", type=kind, code=code, key=key, windowsVirtualKeyCode=vk)

    def drag(self, start: tuple[float, float], end: tuple[float, float]) -> None:
        self.call("Input.dispatchMouseEvent", type="mousePressed", x=start[0], y=start[1], button="left", clickCount=1)
        for t in (0.33, 0.66, 1.0):
            x, y = start[0] + t * (end[0] - start[0]), start[1] + t * (end[1] - start[1])
            self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y, button="left", buttons=1)
        self.call("Input.dispatchMouseEvent", type="mouseReleased", x=end[0], y=end[1], button="left", clickCount=1)

    def wait_for(self, expr: str, what: str, timeout: float = 20) -> None:
        """Until the page's expression is true; on timeout the failure names the page's state."""
        try:
            wait_until(lambda: self.js(expr), what, timeout, interval=0.1)
        except AssertionError as timed_out:
            state = self.js("document.body?.dataset.state")
            status = self.js("document.getElementById('status')?.textContent")
            raise AssertionError(f"{timed_out}: page state {state!r}, {status!r}") from None

    def wait_frames(self, count: int, what: str, timeout: float = 30) -> None:
        """Until `count` more replies have arrived: a span of the stream measured in frames, which a
        loaded machine stretches in time but not in what the character does."""
        seen = int(self.js("document.body.dataset.received"))
        self.wait_for(f"+document.body.dataset.received >= {seen + count}", what, timeout)


@contextmanager
def devtools_page(tmp_path: Path):
    from websockets.sync.client import connect

    port = free_port()
    proc = subprocess.Popen(
        [
            str(CHROMIUM),
            *CHROMIUM_FLAGS,
            f"--user-data-dir={tmp_path / 'profile'}",
            f"--remote-debugging-port={port}",
            "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    pages: list[dict] = []

    def page_listed() -> bool:
        assert proc.poll() is None, f"chromium exited ({proc.returncode}) before its DevTools endpoint came up"
        try:
            targets = httpx.get(f"http://127.0.0.1:{port}/json/list", timeout=1).json()
        except (httpx.TransportError, ValueError):
            return False
        pages.extend(t for t in targets if t.get("type") == "page")
        return bool(pages)

    try:
        wait_until(page_listed, "chromium's DevTools endpoint", timeout=30, interval=0.1)
        with connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as cdp:
            tools = DevTools(cdp)
            tools.call("Emulation.setDeviceMetricsOverride", width=1000, height=600, deviceScaleFactor=1, mobile=False)
            yield tools
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_viewer_streams_in_real_time(server, tmp_path):
    """Real time running: the page streams the demo clip at its 30 fps, every frame comes back,
    the readout shows the round trip, a style switch with a transition is acknowledged, and the
    style triangle's point on an edge mixes that edge's two styles half and half."""
    need_chromium()
    with devtools_page(tmp_path) as page:
        page.call("Page.navigate", url=f"{server}/viewer?autoplay=1&model=lti&style=elderly")
        page.wait_for(
            "document.body && document.body.dataset.state === 'streaming' && +document.body.dataset.received >= 5",
            "viewer did not stream",
        )
        t0, n0 = time.monotonic(), int(page.js("document.body.dataset.received"))
        page.wait_frames(90, "the viewer stopped streaming")  # 3 s of the clip
        page.js(
            "document.getElementById('style').value = 'exhausted';"
            "document.getElementById('style').dispatchEvent(new Event('change'))"
        )
        page.wait_frames(30, "the viewer stopped streaming after a style change")
        rate = (int(page.js("document.body.dataset.received")) - n0) / (time.monotonic() - t0)
        page.wait_for(
            "document.getElementById('hud').innerText.includes('exhausted 1.00')", "no style_set for 'exhausted'"
        )
        hud = page.js("document.getElementById('hud').innerText")
        print(f"viewer in real time: {rate:.1f} frames/s received; HUD: {hud!r}")
        assert 0.7 * 30 < rate < 1.1 * 30, f"expected the clip's 30 frames/s, got {rate:.1f}"
        counted = int(page.js("document.getElementById('rate').textContent"))
        assert 20 <= counted <= 33, f"the page counts {counted} frames in the last second"
        mean = float(page.js("document.getElementById('lat-mean').textContent"))
        assert 0 < mean < 2000, f"mean round trip {mean} ms"
        assert "dropped 0" in hud
        assert "exhausted 1.00" in hud, hud  # the style_set reply's weights
        shot = page.call("Page.captureScreenshot", format="png")["data"]

        # the triangle: corners elderly (top), active (bottom left), youthful (bottom right);
        # dragging the point past the bottom edge's middle clamps it onto the edge
        page.js("""(() => { const p = [...document.querySelectorAll('#triangle select')];
                   ['elderly', 'active', 'youthful'].forEach((s, i) => { p[i].value = s; }); })()""")
        box = page.js(
            "(() => { const r = document.querySelector('#triangle svg').getBoundingClientRect();"
            " return [r.left, r.top, r.width / 160, r.height / 140]; })()"
        )

        def at(x: float, y: float) -> tuple[float, float]:  # viewBox -> page pixels
            return box[0] + x * box[2], box[1] + y * box[3]

        page.drag(at(80, 90), at(80, 139))
        page.wait_for(
            "/active 0\\.50, youthful 0\\.50|youthful 0\\.50, active 0\\.50/"
            ".test(document.getElementById('weights').textContent)",
            "no half-and-half style_set from the triangle",
        )
        weights = page.js("document.getElementById('weights').textContent")
        assert "elderly" not in weights and page.js("document.getElementById('triangle').classList.contains('active')")
        page.wait_for(
            "document.getElementById('sub-output').textContent.includes('active 0.50 + youthful 0.50')",
            "the stylised panel's label does not name the triangle's mix",
        )  # drawn with the next frame
        # a style picked from the menu takes over again
        page.js(
            "document.getElementById('style').value = 'elderly';"
            "document.getElementById('style').dispatchEvent(new Event('change'))"
        )
        page.wait_for(
            "/elderly 1\\.00/.test(document.getElementById('weights').textContent)", "picker did not take over"
        )
        assert not page.js("document.getElementById('triangle').classList.contains('active')")
    png = tmp_path / "viewer_live.png"
    png.write_bytes(base64.b64decode(shot))
    OUT.mkdir(exist_ok=True)
    shutil.copy(png, OUT / "viewer_live.png")
    check_two_skeletons(png)


def test_a_dropped_bvh_clip_becomes_a_style_the_stream_switches_to(server, tmp_path, index):
    """A real dataset-1 walk dropped on the page is uploaded as a new LTI style, its job is
    followed, and the running session is switched to it."""
    need_chromium()
    clip = select(index, dataset="bandai-namco-1", style="proud", content="walk")[0]
    with devtools_page(tmp_path) as page:
        page.call("Page.navigate", url=f"{server}/viewer?autoplay=1&model=lti&style=elderly")
        page.wait_for("document.body && document.body.dataset.state === 'streaming'", "viewer did not stream")
        page.js(
            f"""(() => {{ const data = new DataTransfer();
                data.items.add(new File([{json.dumps(clip.path.read_text())}], "Proud Walk.bvh"));
                window.dispatchEvent(new DragEvent("drop", {{ dataTransfer: data, bubbles: true }})); }})()"""
        )
        page.wait_for("['done', 'failed'].includes(document.body.dataset.upload)", "the upload's job", timeout=120)
        status = page.js("document.getElementById('status').textContent")
        assert page.js("document.body.dataset.upload") == "done", status
        assert page.js("document.getElementById('style').value") == "proud-walk", status
        page.wait_for("/proud-walk 1\\.00/.test(document.getElementById('weights').textContent)", "no style_set")
        page.wait_frames(10, "the viewer stopped streaming on the new style")
    assert "lti.proud-walk" in {s["id"] for s in httpx.get(f"{server}/v1/styles").json()}


def test_keys_and_gamepad_make_control_messages(server, tmp_path):
    """LPN-FiLM's controller mode: offered only for the model that takes control messages; real
    key presses (W, Shift, Q, then D) become the `control` messages the page sends each tick and
    show in its controller HUD; a gamepad in use wins over the keyboard."""
    need_chromium()
    with devtools_page(tmp_path) as page:
        page.call("Page.navigate", url=f"{server}/viewer?model=lti")
        page.wait_for("document.body && document.body.dataset.state === 'ready'", "viewer did not load")
        drives = "[...document.getElementById('source').options].map(o => o.value)"
        assert "control" not in page.js(drives)  # lti takes clips only

        # keys, sampled by the test itself: in clip mode nothing else samples the controller
        W, SHIFT, Q, D = ("KeyW", "w", 87), ("ShiftLeft", "Shift", 16), ("KeyQ", "q", 81), ("KeyD", "d", 68)
        page.js("viewer.controller.reset()")
        for k in (W, SHIFT, Q):
            page.key("keyDown", *k)
        msg = page.js("viewer.controller.sample(0.5)")  # half a second of Q at 2 rad/s
        assert msg == {"type": "control", "velocity": [3.5, 0], "facing": 1.0, "gait": "run"}, msg
        for k in (Q, SHIFT):
            page.key("keyUp", *k)
        page.key("keyDown", *D)
        msg = page.js("viewer.controller.sample(0.5)")  # forward and right at once: walk, diagonal as fast as straight
        assert msg["gait"] == "walk" and msg["facing"] == 1.0
        assert msg["velocity"] == pytest.approx([1.4 / math.sqrt(2), -0.9 / math.sqrt(2)], abs=1e-3)

        # the lpn model offers the controller drive; its HUD follows the held keys before anything streams
        page.js(
            "(() => { const m = document.getElementById('model'); m.value = 'lpn'; m.dispatchEvent(new Event('change')); })()"
        )
        assert "control" in page.js(drives)
        assert page.js("document.getElementById('control-hud').hidden")
        page.js(
            "(() => { const s = document.getElementById('source'); s.value = 'control'; s.dispatchEvent(new Event('change')); })()"
        )
        assert (
            not page.js("document.getElementById('control-hud').hidden")
            and page.js("document.body.dataset.mode") == "control"
        )
        page.wait_for(
            "document.getElementById('control-readout').textContent.startsWith('forward 0.99 m/s · side -0.64 m/s')",
            "the controller HUD does not show the held keys",
        )
        for k in (W, D):
            page.key("keyUp", *k)
        page.wait_for(
            "document.getElementById('control-readout').textContent.startsWith('forward 0.00 m/s · side 0.00 m/s')",
            "the controller HUD does not show the keys released",
        )
        # switching back to a clip model takes the controller drive away
        page.js(
            "(() => { const m = document.getElementById('model'); m.value = 'lti'; m.dispatchEvent(new Event('change')); })()"
        )
        assert "control" not in page.js(drives) and page.js("document.getElementById('source').value") == "demo"
        assert page.js("document.getElementById('control-hud').hidden")

        # a gamepad (standard mapping): left stick up-right, right stick left, right trigger
        pad = "{id: 'test pad', axes: [0.6, -0.8, -1, 0], buttons: Array.from({length: 16}, (_, i) => ({pressed: i === 7, value: +(i === 7)}))}"
        msg = page.js(f"""(async () => {{
            const c = await import('/viewer/static/controller.js');
            const ctl = new c.Controller(document.createElement('div'), () => [null, {pad}]);
            return [ctl.sample(0.25), ctl.gamepad];
        }})()""")
        (msg, pad_id) = msg
        assert pad_id == "test pad" and msg["gait"] == "run"
        assert msg["velocity"] == pytest.approx([0.8 * 3.5, -0.6 * 1.8], abs=1e-3)  # full deflection: full speed
        assert msg["facing"] == pytest.approx(0.5, abs=1e-3)  # right stick left turns left at 2 rad/s
        idle = page.js(
            "import('/viewer/static/controller.js').then(c => c.intentFromGamepad({axes: [0.1, -0.05, 0.1, 0], buttons: []}))"
        )
        assert idle is None  # inside the dead zone: the keyboard keeps control


def test_keys_drive_the_lpn_character_through_the_server(server, tmp_path):
    """End to end with the committed LPN-FiLM: in the controller drive, holding W walks the
    stylised character forward (+Z, the starting facing) at about the keyboard's walk speed, Q
    held as well turns it left, and releasing everything stops it; every control tick is
    answered. Screenshot in out/viewer_lpn.png."""
    need_chromium()
    W, Q = ("KeyW", "w", 87), ("KeyQ", "q", 81)
    root = "viewer.state.lastOut && viewer.state.lastOut.root"
    with devtools_page(tmp_path) as page:
        page.call("Page.navigate", url=f"{server}/viewer?model=lpn&style=elderly")
        page.wait_for("document.body && document.body.dataset.state === 'ready'", "viewer did not load")
        page.js(
            "(() => { const s = document.getElementById('source'); s.value = 'control'; s.dispatchEvent(new Event('change')); })()"
        )
        page.js("viewer.controller.reset(); document.getElementById('play').click()")
        page.wait_for(
            "document.body.dataset.state === 'streaming' && +document.body.dataset.received >= 30",
            "the controller session did not stream",
        )
        start = page.js(root)
        page.key("keyDown", *W)
        page.wait_frames(90, "no replies while W is held")  # 3 s of ticks at 30 fps
        walked = page.js(root)
        page.key("keyDown", *Q)
        page.wait_frames(45, "no replies while W and Q are held")
        for k in (Q, W):
            page.key("keyUp", *k)
        turned = page.js(root)
        page.wait_frames(60, "no replies after the keys were released")
        stopped = page.js(root)
        page.wait_frames(30, "no replies once stopped")
        still = page.js(root)
        hud = page.js("document.getElementById('hud').innerText")
        shot = page.call("Page.captureScreenshot", format="png")["data"]
    print(
        f"lpn in the browser: start {start}, after W {walked}, after W+Q {turned}, stopped {stopped} / {still}; HUD {hud!r}"
    )
    dz, dx = walked[2] - start[2], walked[0] - start[0]
    assert 150 < dz < 600 and abs(dx) < 0.3 * dz, (
        f"3 s of W should walk ~3 m along +Z, walked dx {dx:.0f} cm, dz {dz:.0f} cm"
    )
    # Q turns left: facing +Z, the character's left is +X
    assert turned[0] - walked[0] > 20, f"W+Q should curve toward +X, moved {turned[0] - walked[0]:.0f} cm in x"
    assert np.hypot(still[0] - stopped[0], still[2] - stopped[2]) < 25, "released keys should bring it to a stop"
    assert "dropped 0" in hud, hud
    png = tmp_path / "viewer_lpn.png"
    png.write_bytes(base64.b64decode(shot))
    OUT.mkdir(exist_ok=True)
    shutil.copy(png, OUT / "viewer_lpn.png")


def test_viewer_maths_match_the_python_motion_core(server, tmp_path):
    """The page's own modules, run in the browser: its BVH reader and forward kinematics put every
    joint where the Python motion core does (BVH assets in two Euler orders, every frame of the
    demo clip), the triangle's barycentric maths round-trips and clamps onto the triangle, and
    the scene marks exactly the feet a frame's `contacts` say are planted."""
    need_chromium()
    from models.motion.orientation import rig, solid_corners
    from models.motion.rotations import quat_to_matrix
    from models.motion.skeleton import Motion, fk, load

    assets = Path(__file__).resolve().parents[1] / "models" / "motion" / "assets"
    clip = httpx.get(f"{server}/v1/demo/clip").json()
    with devtools_page(tmp_path) as page:
        page.call("Page.navigate", url=f"{server}/viewer")
        page.wait_for("document.body && document.body.dataset.state === 'ready'", "viewer did not load")
        kin = "const k = await import('/viewer/static/kinematics.js');"
        for name in ("bandai_namco.bvh", "cmu.bvh"):
            text = (assets / name).read_text()
            js_pos = page.js(f"""(async () => {{ {kin} const c = k.parseBVH({json.dumps(text)});
                return c.root.map((r, i) => k.fk(c, r, c.rotations[i])); }})()""")
            py_pos = load(assets / name).global_positions()
            assert np.allclose(js_pos, py_pos, atol=1e-3), f"{name}: max {np.abs(np.array(js_pos) - py_pos).max()}"
        # a file whose travel sits on its root joint above the hips (dataset 1's walk 002): the reader
        # puts it on the hips, whose translation the page streams, and the body stays where it was
        walk = next(c for c in build_index(["bandai-namco-1"]) if c.name == "dataset-1_walk_normal_002")
        read = page.js(f"""(async () => {{ {kin} const c = k.parseBVH({json.dumps(Path(walk.path).read_text())});
            return {{root: c.root, pos: c.root.map((r, i) => k.fk(c, r, c.rotations[i]))}}; }})()""")
        assert np.ptp(np.array(read["root"])[:, 2]) > 150.0
        assert np.allclose(np.array(read["pos"])[:, 1:], load(walk.path).global_positions()[:, 1:], atol=1e-3)
        js_pos = np.array(
            page.js(f"""(async () => {{ {kin} const c = k.clipFromDemo(await (await fetch('/v1/demo/clip')).json());
            return c.root.map((r, i) => k.fk(c, r, c.rotations[i])); }})()""")
        )
        sk = bandai_namco_skeleton()
        translations = np.repeat(np.array(clip["offsets"])[None], len(clip["frames"]["root"]), axis=0)
        translations[:, clip["root_joint"]] = clip["frames"]["root"]
        _, py_pos = fk(np.array(clip["frames"]["rotations"]), translations, sk.parents)
        assert js_pos.shape == py_pos.shape and np.allclose(js_pos, py_pos, atol=1e-3)

        tri = page.js("""(async () => {
            const t = await import('/viewer/static/triangle.js'), T = [[80, 8], [8, 132], [152, 132]];
            const inside = [[80, 90], [60, 120], [100, 60]].map((p) => {
              const w = t.barycentric(p, T); return [w, t.pointAt(w, T), p]; });
            return {inside, below: t.clampedBarycentric([80, 200], T), beyond: t.clampedBarycentric([200, 140], T),
                    mix: t.mixFrom(['elderly', 'elderly', 'active'], [0.2, 0.3, 0.5]),
                    tiny: t.mixFrom(['elderly', 'active', 'youthful'], [0.998, 0.002, 0])}; })()""")
        for w, back, p in tri["inside"]:
            assert min(w) > 0 and sum(w) == pytest.approx(1) and back == pytest.approx(p)
        assert tri["below"] == pytest.approx([0, 0.5, 0.5])  # straight below the bottom edge's middle
        assert tri["beyond"] == pytest.approx([0, 0, 1])  # past the bottom right corner
        assert tri["mix"] == {"elderly": 0.5, "active": 0.5} and tri["tiny"] == {"elderly": 0.998}

        # the output stage builds its figure when the first stylised frames arrive: wait for it
        page.wait_for("!!(viewer.view.stages.output.figure && viewer.state.clip)", "the output stage has no figure")
        rings = page.js("""(() => { const c = viewer.state.clip, s = viewer.view.stages.output;
            return import('/viewer/static/kinematics.js').then((k) => {
              const p = k.fk(c, c.root[0], c.rotations[0]);
              s.show(p, [1, 0]);
              const [l, r] = s.contacts;
              return {visible: [l.visible, r.visible], at: [l.position.x, l.position.z],
                      foot: [p[c.feet[0]][0], p[c.feet[0]][2]], feet: c.feet.map((j) => c.joints[j])};
            }); })()""")
        assert rings["visible"] == [True, False] and rings["at"] == pytest.approx(rings["foot"])
        assert rings["feet"] == ["Foot_L", "Foot_R"]

        # the head / hand / foot solids: the page turns each one as the Python renderer does
        placed = page.js(f"""(async () => {{ {kin} const c = k.clipFromDemo(await (await fetch('/v1/demo/clip')).json());
            return {{parts: c.solids.map((s) => s.part), corners: c.solids.map((s) => s.corners),
                     frames: [0, 17, 60].map((i) => {{ const t = k.fkTransforms(c, c.root[i], c.rotations[i]);
                       return c.solids.map((s) => k.placeSolid(s, t.rotations, t.positions)); }})}}; }})()""")
        solids = rig(Motion(sk, np.array(clip["frames"]["rotations"]), translations, clip["fps"]))
        assert placed["parts"] == [s.part for s in solids] and {"head", "nose", "thumb_l", "foot_r"} <= set(
            placed["parts"]
        )
        g_rot, g_pos = fk(np.array(clip["frames"]["rotations"]), translations, sk.parents)
        for i, frame in zip((0, 17, 60), placed["frames"]):
            q = np.array([p["quaternion"] for p in frame])
            js = np.array([p["position"] for p in frame])[:, None] + np.einsum(
                "sab,skb->ska", quat_to_matrix(q), np.array(placed["corners"])
            )
            assert np.allclose(js, solid_corners(g_rot[i], g_pos[i], solids), atol=0.05)  # cm
