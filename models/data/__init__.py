"""Mocap datasets: archives, index and splits, cached loading. `python -m models.data summary`."""

from typing import Any

from .archives import DATASETS, DataError, DatasetSpec, dataset_dir
from .index import SPLITS, Clip, build_index, select

_LOADER = ("load_motion", "load_motions", "warm_cache")


def __getattr__(name: str) -> Any:
    """The loader's functions, imported on first use: they need torch, which `data fetch` does not."""
    if name in _LOADER:
        from . import loader

        return getattr(loader, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DATASETS", "DataError", "DatasetSpec", "dataset_dir", "SPLITS", "Clip", "build_index", "select", "load_motion",
    "load_motions", "warm_cache",
]  # fmt: skip
