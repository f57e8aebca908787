"""The SDK stands alone: `clients.sdk` imports nothing of the server (fast check, in a subprocess
that refuses the server's packages), and `pip install stylestream` into a fresh plain venv brings
numpy, httpx and websockets only, and streams against a live server, on Python 3.11, 3.12 and 3.13
(slow: builds and installs; a version not on the machine is skipped)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SERVER_PACKAGES = [
    "torch",
    "numba",
    "fastapi",
    "pydantic",
    "matplotlib",
    "scipy",
    "starlette",
    "uvicorn",
    "prometheus_client",
    "models",
    "service",
]

BLOCKED_IMPORT = textwrap.dedent("""
    import importlib.abc, json, sys
    BLOCKED = set(sys.argv[1].split(","))

    class Refuse(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"{name} is blocked: the SDK must not need it")

    sys.meta_path.insert(0, Refuse())
    from clients.sdk import AsyncClient, Client
    Client("http://127.0.0.1:1").close()
    print(json.dumps(sorted({m.split(".")[0] for m in sys.modules})))
""")


def test_the_sdk_imports_without_the_servers_packages():
    done = subprocess.run(
        [sys.executable, "-c", BLOCKED_IMPORT, ",".join(SERVER_PACKAGES)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert not set(json.loads(done.stdout)) & set(SERVER_PACKAGES)


STREAM = textwrap.dedent("""
    import json, sys
    import numpy as np
    from clients.sdk import Client

    rot = np.tile([0.0, 0.0, 0.0, 1.0], (22, 1))
    with Client(sys.argv[1], timeout=30) as client:
        styles = [s.id for s in client.styles(model="lti")]
        with client.session(model="lti", style="elderly", max_in_flight=4) as session:
            one = session.stylise(np.array([0.0, 90.0, 0.0]), rot)
            for t in range(8):
                session.send(np.array([0.0, 90.0, float(t)]), rot)
            seqs = [session.receive().seq for _ in range(8)]
    import clients.sdk
    print(json.dumps({"styles": styles, "first": one.seq, "seqs": seqs, "sdk": clients.sdk.__file__}))
""")


def _project_copy(into: Path) -> Path:
    """The project's source as a user would get it (no caches, no venv, no data)."""
    into.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", ".data", "*.egg-info")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, into / name)
    for package in ("clients", "models", "service"):
        shutil.copytree(REPO / package, into / package, ignore=ignore)
    return into


def interpreter(version: str) -> str | None:
    """A working `python<version>`: this one, one on PATH, or one pyenv installed."""
    if f"{sys.version_info.major}.{sys.version_info.minor}" == version:
        return sys.executable
    found = [
        shutil.which(f"python{version}"),
        *map(str, Path.home().glob(f".pyenv/versions/{version}.*/bin/python{version}")),
    ]
    for candidate in filter(None, found):
        if subprocess.run([candidate, "--version"], capture_output=True).returncode == 0:
            return candidate
    return None


@pytest.mark.slow
@pytest.mark.parametrize("version", ["3.11", "3.12", "3.13"])
def test_pip_install_brings_the_sdk_alone_and_it_streams(tmp_path, version):
    python_x = interpreter(version)
    if python_x is None:
        pytest.skip(f"no Python {version} on this machine")
    project = _project_copy(tmp_path / "stylestream")
    subprocess.run([python_x, "-m", "venv", str(tmp_path / "venv")], check=True, timeout=120)  # no system site
    python = tmp_path / "venv" / "bin" / "python"
    install = subprocess.run(
        [str(python), "-m", "pip", "install", "-q", str(project)], capture_output=True, text=True, timeout=600
    )
    assert install.returncode == 0, install.stderr[-3000:]
    listed = subprocess.run(
        [str(python), "-m", "pip", "list", "--format=json"], capture_output=True, text=True, check=True
    ).stdout
    installed = {p["name"].lower().replace("_", "-") for p in json.loads(listed)}
    assert {"numpy", "httpx", "websockets", "stylestream"} <= installed
    assert not installed & {"torch", "numba", "fastapi", "pydantic", "matplotlib", "scipy", "uvicorn", "redis"}
    cli = subprocess.run(
        [str(tmp_path / "venv" / "bin" / "stylestream"), "--help"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=60,
    )  # the commands say which extra they need
    assert cli.returncode == 2 and "pip install 'stylestream[server]'" in cli.stderr, cli.stderr[-2000:]

    from models.registry import load_models
    from models.settings import get_settings

    from .live_server import live_server

    with live_server({"lti": load_models(get_settings().weights_dir)["lti"]}) as (base, _):
        run = subprocess.run(
            [str(python), "-I", "-c", STREAM, base], cwd=tmp_path, capture_output=True, text=True, timeout=120
        )  # -I: the installed package, not this checkout
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout)
    assert "lti.elderly" in out["styles"] and out["first"] == 0 and out["seqs"] == list(range(1, 9))
    assert out["sdk"].startswith(str(tmp_path / "venv")) and f"python{version}" in out["sdk"]
