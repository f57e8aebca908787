"""Parsed-motion cache: each BVH is parsed once into a git-ignored .npz under the cache folder,
keyed by the source file's size and mtime. Cold parsing uses a process pool; hierarchies are
parsed once per distinct header text, so loading thousands of cached clips costs little more
than reading the arrays.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..motion import bvh as bvhio
from ..motion.skeleton import Motion, Skeleton, from_bvh, skeleton_from_bvh, travel_on
from ..settings import Settings, get_settings
from .index import Clip

HIPS_NAME = "Hips"  # the joint whose translation is the body's travel, on the rigs that name it

CACHE_VERSION = 2  # bump when the stored arrays change meaning


def _cache_path(clip: Clip, settings: Settings) -> Path:
    return Path(settings.cache_dir) / "parsed" / clip.dataset / f"{clip.name}.npz"


def _stamp(path: Path) -> np.ndarray:
    st = path.stat()
    return np.array([st.st_size, st.st_mtime_ns, CACHE_VERSION], dtype=np.int64)


def _parse_to_cache(path: Path, cache: Path) -> None:
    text = path.read_text(encoding="utf-8")
    motion = from_bvh(bvhio.parse(text, str(path)))
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(f".{os.getpid()}.tmp.npz")  # own name: test workers parse in parallel
    np.savez(
        tmp,
        header=np.array(text[: text.index("MOTION")]),
        fps=np.array(motion.fps),
        rotations=motion.rotations.astype(np.float32),
        translations=motion.translations.astype(np.float32),
        stamp=_stamp(path),
    )
    os.replace(tmp, cache)  # atomic: a reader never sees half an entry


def _is_fresh(clip: Clip, cache: Path) -> bool:
    if not cache.exists():
        return False
    with np.load(cache) as z:
        return bool(np.array_equal(z["stamp"], _stamp(clip.path)))


@lru_cache(maxsize=64)
def _skeleton(header: str) -> tuple[Skeleton, tuple[str, ...]]:
    return skeleton_from_bvh(bvhio.parse(header + "MOTION\nFrames: 0\nFrame Time: 1\n", "<cached header>"))


def load_motion(clip: Clip, settings: Settings | None = None) -> Motion:
    """The clip as a Motion, parsed on a cache miss; travel above the Hips moved onto them (`travel_on`)."""
    settings = settings or get_settings()
    cache = _cache_path(clip, settings)
    if not _is_fresh(clip, cache):
        _parse_to_cache(clip.path, cache)
    with np.load(cache) as z:
        skeleton, orders = _skeleton(str(z["header"]))
        motion = Motion(
            skeleton, z["rotations"].astype(np.float64), z["translations"].astype(np.float64), float(z["fps"]), orders
        )
    return travel_on(motion, skeleton.index(HIPS_NAME)) if HIPS_NAME in skeleton.names else motion


def warm_cache(clips: list[Clip], settings: Settings | None = None, workers: int | None = None) -> int:
    """Parse every clip whose cache is missing or stale; returns how many were parsed."""
    settings = settings or get_settings()
    todo = [(c.path, _cache_path(c, settings)) for c in clips if not _is_fresh(c, _cache_path(c, settings))]
    if not todo:
        return 0
    workers = workers or min(len(todo), os.cpu_count() or 1)
    if workers <= 1 or len(todo) < 8:
        for path, cache in todo:
            _parse_to_cache(path, cache)
    else:
        with ProcessPoolExecutor(workers) as pool:
            list(pool.map(_parse_to_cache, *zip(*todo), chunksize=16))
    return len(todo)


def load_motions(clips: list[Clip], settings: Settings | None = None) -> list[Motion]:
    warm_cache(clips, settings)
    return [load_motion(c, settings) for c in clips]
