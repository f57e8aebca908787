"""Before pytest-xdist's workers start: numba's kernels compiled into their cache and the mocap
archives unpacked, each part in its own process, all at once.

    .venv/bin/python -m tests.warm erd      # one part (what `pytest_configure` in conftest.py runs)

numba keys its on-disk cache on each source file's time stamp, so on a fresh clone every kernel is
compiled on first use: about 40 s of CPU for the three models and the service (Style-ERD 19 s,
LPN-FiLM 12, LTI 9, the service's frame check and retargeting 2). The workers start together, so
each compiled them all, as did every server process a test started before the cache was written,
and a worker that needed the data waited on the archives' unpack lock (14 s). Done here first, in
parallel processes (on two cores about 25 s), the workers and servers load the compiled kernels."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np

PARTS = ("erd", "lpn", "lti", "service", "data")


def warm(part: str) -> None:
    """Compile (or load) one part's kernels, or unpack the archives (`data`)."""
    if part == "data":
        from models.data import build_index

        build_index()
        return
    if part == "service":
        from service import frame_check, skeletons

        frame_check.warm()
        skeletons.warm()
        return
    from models.interface import FrameBatch
    from models.settings import get_settings

    model = importlib.import_module(f"models.{part}").load(get_settings().weights_dir / part)
    rotations = np.zeros((2, len(model.skeleton.names), 4), np.float32)
    rotations[..., 3] = 1.0
    weights = np.zeros((2, len(model.styles())), np.float32)
    weights[:, 0] = 1.0
    state = model.init_state(2)
    for _ in range(3):  # a few frames of two sessions: the paths a first frame skips compile too
        _, state = model.step_batch(state, FrameBatch(np.tile([0.0, 90.0, 0.0], (2, 1)), rotations), weights)


def warm_all() -> None:
    """Every part at once, each in its own process; a part that fails is left to the tests, which
    say why (a missing dataset skips the tests that need it)."""
    root = Path(__file__).resolve().parents[1]
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "tests.warm", part], cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        for part in PARTS
    ]
    for proc in procs:
        proc.wait()


if __name__ == "__main__":
    warm(sys.argv[1])
