"""The container image, built with podman and run as ops would run it: a published port, /readyz,
a real clip streamed through a WebSocket session, then `podman stop` (SIGTERM) with a session open.

Podman and a registry-free python:3.11-slim come from ../shared/tools/container-base.sh (root and
apt needed: otherwise the module is skipped, saying why). The first build on a machine installs
torch and the dependencies (minutes); later builds reuse those layers (about a minute), and load
the numba kernels this checkout compiled (`docker/numba_seed.py`; under pytest-xdist the controller
compiles them all first, `tests/warm.py`) instead of compiling them again.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from clients.loadtest import free_port, wait_ready
from clients.sdk import Client
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server

REPO = Path(__file__).resolve().parents[1]
CONTAINER_BASE = REPO.parent / "shared" / "tools" / "container-base.sh"
IMAGE = "localhost/stylestream:test"
DRAIN_TIMEOUT_S = 10  # the server's own bound on a drain; podman would SIGKILL only after STOP_TIMEOUT_S
STOP_TIMEOUT_S = 30
FRAMES = 60


def _run(*args: str, timeout: float = 60, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(args, capture_output=True, text=True, timeout=timeout)
    if check and done.returncode != 0:
        raise AssertionError(f"{' '.join(args)} exited {done.returncode}:\n{done.stdout}{done.stderr}")
    return done


@pytest.fixture(scope="module")
def podman() -> str:
    if os.geteuid() != 0:
        pytest.skip("installing podman (../shared/tools/container-base.sh) needs root")
    if shutil.which("apt-get") is None:
        pytest.skip("no apt-get to install podman with")
    assert CONTAINER_BASE.is_file(), f"{CONTAINER_BASE} is missing (CI has ../shared beside the clone)"
    done = subprocess.run(["bash", str(CONTAINER_BASE)], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, f"container-base.sh failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return shutil.which("podman") or "podman"


@pytest.fixture(scope="module")
def image(podman, tmp_path_factory) -> str:
    log = tmp_path_factory.mktemp("image") / "build.log"
    t0 = time.monotonic()
    with log.open("w") as out:
        done = subprocess.run(
            ["bash", str(REPO / "docker" / "build-image.sh")],
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "IMAGE": IMAGE},
            timeout=1200,
        )
    assert done.returncode == 0, f"image build failed:\n{log.read_text()[-4000:]}"
    print(f"image built in {time.monotonic() - t0:.0f} s")
    return IMAGE


@dataclass
class Container:
    name: str
    url: str

    def state(self) -> dict:
        return json.loads(_run("podman", "inspect", "--format", "{{json .State}}", self.name).stdout)

    def logs(self) -> str:
        done = _run("podman", "logs", self.name)
        return done.stdout + done.stderr


@pytest.fixture(scope="module")
def container(image):
    """The image as ops run it: detached, the port published on loopback, config by environment,
    the root filesystem read-only with a writable volume on its home, as docker/k8s/deployment.yaml
    runs it (a fresh volume takes the image's folders and their owner, as in compose)."""
    name, port = f"stylestream-test-{os.getpid()}", free_port()
    home = f"{name}-home"
    _run("podman", "rm", "-f", "--ignore", name)
    _run("podman", "volume", "rm", "-f", home)
    _run(
        "podman",
        "run",
        "-d",
        "--name",
        name,
        "-p",
        f"127.0.0.1:{port}:8000",
        "--read-only",
        "-v",
        f"{home}:/var/lib/stylestream",
        "-e",
        f"STYLESTREAM_DRAIN_TIMEOUT_S={DRAIN_TIMEOUT_S}",
        image,
    )
    box = Container(name, f"http://127.0.0.1:{port}")
    try:
        t0 = time.monotonic()
        wait_ready(box.url, lambda: box.state()["Running"], timeout=120)
        print(f"container ready {time.monotonic() - t0:.1f} s after podman run")
        yield box
    except Exception:
        print(box.logs())
        raise
    finally:
        _run("podman", "rm", "-f", "--ignore", name, check=False)
        _run("podman", "volume", "rm", "-f", home, check=False)


def test_image_runs_as_non_root_and_its_healthcheck_passes(container):
    [inspected] = json.loads(_run("podman", "image", "inspect", IMAGE).stdout)
    assert inspected["Config"]["User"] == "10001:10001"
    assert inspected["Config"]["StopSignal"] == "SIGTERM"
    assert inspected["Healthcheck"]["Test"] == ["CMD", "python", "/opt/stylestream/healthcheck.py"]
    assert _run("podman", "exec", container.name, "id", "-u").stdout.strip() == "10001"
    # PID 1 is tini, the server its child, so SIGTERM reaches a process that handles it
    assert _run("podman", "exec", container.name, "cat", "/proc/1/comm").stdout.strip() == "tini"
    assert _run("podman", "healthcheck", "run", container.name, check=False).returncode == 0
    # the readiness form compose uses, and a failing one: the probe can say no
    assert (
        _run("podman", "exec", container.name, "python", "/opt/stylestream/healthcheck.py", "/readyz").returncode == 0
    )
    missing = _run("podman", "exec", container.name, "python", "/opt/stylestream/healthcheck.py", "/nope", check=False)
    assert missing.returncode == 1 and "404" in missing.stderr


def test_numba_kernels_come_compiled_with_the_image(container):
    """The image carries numba's cache from its build and the entrypoint seeds the writable cache
    on the home volume with it, so a fresh container loads the kernels instead of compiling them."""

    def cache_files(folder: str) -> set[str]:
        listing = _run("podman", "exec", container.name, "find", folder, "-name", "*.nbi", "-printf", "%P\\n")
        return set(listing.stdout.split())

    baked = cache_files("/opt/stylestream/numba-cache")
    assert any("lti" in f for f in baked) and any("erd" in f for f in baked), sorted(baked)
    assert baked <= cache_files("/var/lib/stylestream/cache/numba")


def test_a_clip_streams_through_the_container_as_through_the_server_in_process(container, bn_walk):
    """The image carries the committed weights: the same clip gives the same frames as the code here."""
    root, rot = bn_walk.translations[:FRAMES, 1], bn_walk.rotations[:FRAMES]

    def stream(base: str) -> np.ndarray:
        with Client(base).session(model="lti", style="elderly") as session:
            frames = [session.stylise(root[t], rot[t]) for t in range(FRAMES)]
        assert [f.seq for f in frames] == list(range(FRAMES))
        return np.array([f.rotations for f in frames])

    from_container = stream(container.url)
    with live_server(load_models(get_settings().weights_dir)) as (base, _):
        here = stream(base)
    assert np.isfinite(from_container).all()
    assert np.abs(from_container - rot).max() > 1e-3  # stylised, not passed through
    np.testing.assert_allclose(from_container, here, atol=1e-5)


def test_podman_stop_drains_the_open_session_and_exits_cleanly(container, bn_walk):
    """SIGTERM reaches the server through tini: the open session is closed with 1012 (service
    restart) well before podman's SIGKILL, and the container exits 0, logging its shutdown."""
    from websockets.exceptions import ConnectionClosed

    session = Client(container.url).session(model="lti", style="elderly")
    for t in range(10):
        session.stylise(bn_walk.translations[t, 1], bn_walk.rotations[t])
    t0 = time.monotonic()
    _run("podman", "stop", "-t", str(STOP_TIMEOUT_S), container.name, timeout=STOP_TIMEOUT_S + 30)
    stopped_in = time.monotonic() - t0
    with pytest.raises(ConnectionClosed) as closed:
        while True:
            session.ws.recv(timeout=5)  # a snapshot acknowledgement may come first
    session.close()  # the socket is closed already: no `end` to wait for, no reconnect

    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1012
    assert stopped_in < DRAIN_TIMEOUT_S, f"stop took {stopped_in:.1f} s"
    state = container.state()
    assert not state["Running"] and state["ExitCode"] == 0, state
    logs = container.logs()
    assert "draining 1 session(s)" in logs and "Finished server process" in logs, logs[-2000:]
