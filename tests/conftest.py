"""Shared fixtures: the real mocap index (unpacked into the git-ignored cache on first use).

On a machine without the mocap data, a test that needs it skips with one line saying which
dataset is missing and where it was looked for (`DataMissing`, raised wherever a test, a fixture
or the code under test first reaches for a dataset); on CI the data is there and they run."""

from __future__ import annotations

import functools
import os
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from models.data import Clip, build_index, dataset_dir, load_motion, select
from models.data.archives import DataMissing
from models.motion.skeleton import Motion
from models.settings import get_settings

if TYPE_CHECKING:
    from models.erd.runtime import ERDModel
    from models.lpn.runtime import LPNModel


def _one_ssl_context_per_setting() -> None:
    """httpx builds an SSL context, reading every CA certificate, for each client it makes: one
    per `httpx.get` and per poll of a starting server (`wait_ready`), thousands in the suite at
    30-50 ms of CPU each, for URLs that are all plain http on loopback. In the tests' processes
    each set of arguments gets one, shared (clients and threads may share a context)."""
    from httpx._transports import default

    made = functools.lru_cache(maxsize=None)(default.create_ssl_context)

    def shared(verify=True, cert=None, trust_env=True):  # noqa: ANN001, ANN202 (httpx's own signature)
        try:
            return made(verify, cert, trust_env)
        except TypeError:  # an argument that cannot be a cache key
            return made.__wrapped__(verify, cert, trust_env)

    default.create_ssl_context = shared


_one_ssl_context_per_setting()


# Test files handed to pytest-xdist's workers before all others, in this order: one whose module
# fixture takes minutes (the image build) is the run's last test if it starts late, and has the
# other worker's whole share of the suite to overlap with if it starts first. The others hold few
# tests that take long (10,000 fuzzed messages; servers drained, killed, sharing a port), so
# sorted by test count they came last and ran alone at the end (fresh clone, 2026-12-01: 40-50 s,
# 20-25 s and 15-18 s).
SCHEDULE_FIRST = ("test_container.py", "test_fuzz.py", "test_drain.py", "test_workers.py")


def _distributed(config: pytest.Config) -> bool:
    return bool(os.environ.get("PYTEST_XDIST_WORKER") or getattr(config.option, "numprocesses", None))


def pytest_configure(config: pytest.Config) -> None:
    """With pytest-xdist (`make test`), the controller compiles the kernels and unpacks the data
    once before the workers start, which would each do it (`tests/warm.py`). It hands out the test
    files in the order `pytest_collection_modifyitems` leaves them, not re-sorted by size."""
    if not os.environ.get("PYTEST_XDIST_WORKER") and getattr(config.option, "numprocesses", None):
        from .warm import warm_all

        config.option.loadscopereorder = False
        warm_all()


@pytest.hookimpl(trylast=True)  # after `-m` has deselected
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under pytest-xdist, the files in `SCHEDULE_FIRST` first, in its order, then the others by
    descending test count as xdist's own `--loadscope-reorder` sorts them (a stable sort: each
    file's tests keep their order). Every worker collects the same order, as xdist requires."""
    if not _distributed(config):
        return
    counts = Counter(item.path for item in items)
    first = {name: at for at, name in enumerate(SCHEDULE_FIRST)}
    items.sort(key=lambda item: (first.get(item.path.name, len(first)), -counts[item.path]))


@pytest.fixture(scope="session")
def mocap_data() -> None:
    """For a test whose code reads the data where a missing dataset would not reach the test as
    `DataMissing` (a CLI's exit code, an error it expects): the check made up front."""
    dataset_dir("bandai-namco-2")


@pytest.fixture(scope="session")
def index() -> list[Clip]:
    return build_index()


@pytest.fixture(scope="session")
def bn_walk(index) -> Motion:
    """A neutral Bandai Namco dataset-2 walk from the validation split."""
    return load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])


@pytest.fixture(scope="session")
def lpn_model() -> LPNModel:
    """The committed LPN-FiLM model, loaded once: a test that adds, replaces or removes styles does
    it on a copy (`with_own_styles`)."""
    from models.lpn import load  # its compiled kernels, only for the tests that use it

    return load(get_settings().weights_dir / "lpn")


@pytest.fixture(scope="session")
def erd_model() -> ERDModel:
    """The committed Style-ERD model, loaded once: a test that adds or removes styles does it on a
    copy (`with_own_styles`)."""
    from models.erd.runtime import load

    return load(get_settings().weights_dir / "erd")


@pytest.fixture(scope="session")
def erd_cache(index, tmp_path_factory) -> Path:
    """A Style-ERD feature cache (`models/erd/dataset.py`) of a few TRAIN clips of every style, two
    walks, two runs and a gesture each, for the tests of what is fitted from the cache: the whole
    one (every clip of dataset 2) takes minutes to build, and only training needs it. A test points
    `dataset.cache_dir` at it (`small_erd_cache`)."""
    from models.erd.dataset import DATASET, STYLES, build_cache

    def few(style: str, content: str, n: int) -> list[Clip]:
        chosen = select(index, dataset=DATASET, split="train", style=style, content=content)
        return sorted(chosen, key=lambda c: c.name)[:n]

    train = [
        c
        for s in STYLES
        for content, n in (("walk", 2), ("run", 2), ("wave-both-hands", 1))
        for c in few(s, content, n)
    ]
    return build_cache(tmp_path_factory.mktemp("erd-cache"), {"train": train})


@pytest.fixture(scope="module")
def small_erd_cache(erd_cache) -> Iterator[Path]:
    """`erd_cache` as the Style-ERD feature cache for a test module."""
    from models.erd import dataset

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(dataset, "cache_dir", lambda: erd_cache)
        yield erd_cache


@pytest.fixture(scope="session")
def cmu_walk(index) -> Motion:
    return load_motion(select(index, dataset="xia", style="neutral", content="walk")[0])


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    report = yield
    if call.excinfo is not None and call.excinfo.errisinstance(DataMissing) and report.failed:
        report.outcome = "skipped"
        path, line, _ = item.location
        report.longrepr = (path, (line or 0) + 1, f"needs the mocap data: {call.excinfo.value}")
    return report
