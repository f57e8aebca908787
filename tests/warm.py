"""Before pytest-xdist's workers start: numba's kernels compiled into their cache and the mocap
archives unpacked, in a few processes at once.

    .venv/bin/python -m tests.warm erd lpn   # these parts in one process (what `warm_all` runs)

numba keys its on-disk cache on each source file's time stamp, so on a fresh clone every kernel is
compiled on first use: about 130 s of CPU for the three models and the service, each measured
alone (LTI 59 s, one step kernel with or without the fade; the service's retargeting 38,
Style-ERD 37, LPN-FiLM 34; measured on 2026-12-01). The workers start together, so each compiled
them all, as did every server process a test started before the cache was written, and a worker
that needed the data waited on the archives' unpack lock (14 s). Done here first, the workers and
servers load the compiled kernels. Style-ERD and LPN-FiLM share one process (`GROUPS`): the
kernels both call (the foot planter, the unseen-content fade) are compiled once, and torch is
imported once: 44 s for the two. A test that hands Style-ERD's or LPN-FiLM's kernels other array
types (read-only, float32, strided) still compiles those itself; LTI's step kernel compiles once
and converts such arrays instead."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

GROUPS = (("lti",), ("erd", "lpn"), ("service",), ("data",))  # one process each, LTI's the longest


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
    """Every part, the `GROUPS` at once; a part that fails is left to the tests, which say why (a
    missing dataset skips the tests that need it)."""
    root = Path(__file__).resolve().parents[1]
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "tests.warm", *group], cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        for group in GROUPS
    ]
    for proc in procs:
        proc.wait()


if __name__ == "__main__":
    for name in sys.argv[1:]:
        warm(name)
