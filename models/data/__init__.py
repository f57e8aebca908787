"""Mocap datasets: archives, index and splits, cached loading. `python -m models.data summary`."""

from .archives import DATASETS, DataError, DatasetSpec, dataset_dir
from .index import SPLITS, Clip, build_index, select
from .loader import load_motion, load_motions, warm_cache

__all__ = [
    "DATASETS",
    "DataError",
    "DatasetSpec",
    "dataset_dir",
    "SPLITS",
    "Clip",
    "build_index",
    "select",
    "load_motion",
    "load_motions",
    "warm_cache",
]
