"""Commands that build or fit something answer `--help` with their usage and do nothing else:
before, some took `--help` for a path (a 44 MB `--help.npz`) or ignored it and rebuilt a cache."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    "command",
    ["models.erd.distill", "models.erd.dataset", "models.lpn.dataset", "models.lti.raised_arm", "models.erd.train"],
)
def test_help_prints_the_usage_and_writes_nothing(command, tmp_path):
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "STYLESTREAM_DATA_DIR": str(tmp_path / "data")}
    done = subprocess.run(
        [sys.executable, "-m", command, "--help"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip(), "nothing printed"
    assert list(tmp_path.iterdir()) == [], "the help wrote files"
