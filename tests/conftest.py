"""Shared fixtures: the real mocap index (unpacked into the git-ignored cache on first use)."""

from __future__ import annotations

import pytest

from models.data import Clip, build_index, load_motion, select
from models.motion.skeleton import Motion


@pytest.fixture(scope="session")
def index() -> list[Clip]:
    return build_index()


@pytest.fixture(scope="session")
def bn_walk(index) -> Motion:
    """A neutral Bandai Namco dataset-2 walk from the validation split."""
    return load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])


@pytest.fixture(scope="session")
def cmu_walk(index) -> Motion:
    return load_motion(select(index, dataset="xia", style="neutral", content="walk")[0])
