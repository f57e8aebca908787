"""Before pytest-xdist's workers start: numba's kernels compiled into their cache and the mocap
archives unpacked, each part in its own process, all at once.

    .venv/bin/python -m tests.warm erd      # one part (what `pytest_configure` in conftest.py runs)

numba keys its on-disk cache on each source file's time stamp, so on a fresh clone every kernel is
compiled on first use: about 150 s of CPU for the three models and the service (LTI 75 s, its
step with and without the fade; the service's retargeting 39, Style-ERD 18, LPN-FiLM 16; measured
on 2026-12-01). The workers start together, so each compiled them all, as did every server process
a test started before the cache was written, and a worker that needed the data waited on the
archives' unpack lock (14 s). Done here first, in parallel processes (on two cores about 80 s, LTI's
the longest), the workers and servers load the compiled kernels. A test that hands Style-ERD's or
LPN-FiLM's kernels other array types (read-only, float32, strided) still compiles those itself;
LTI's step kernels compile once and convert such arrays instead."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

PARTS = ("erd", "lpn", "lti", "service", "data")


def warm(part: str) -> None:
    """Compile (or load) one part's kernels, or unpack the archives (`data`): a model is loaded as
    served (`models.registry`, its unseen-content fade included) and stepped once, as the server's
    start (and the image build) warms it."""
    if part == "data":
        from models.data import build_index

        build_index()
        return
    if part == "service":
        from models.motion import rate_kernels
        from service import frame_check, skeletons

        frame_check.warm()
        rate_kernels.warm()
        skeletons.warm()
        return
    from models.registry import load_model
    from models.settings import get_settings
    from service.runtime import warm_up

    model = load_model(get_settings().weights_dir, part)  # as served: the unseen-content fade last
    assert model is not None, part
    warm_up(model)


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
