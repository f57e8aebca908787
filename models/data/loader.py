"""Parsed-array cache: each BVH is parsed once into a git-ignored .npz next to the unpacked data.

An entry stores the hierarchy text and the motion matrix (float32) plus the source file's size
and mtime; a changed file misses the cache and is parsed again. Cold parsing of many files uses a
process pool (the machines have 2 cores).
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from ..motion import bvh as bvhio
from ..motion.skeleton import Motion, from_bvh
from ..settings import Settings, get_settings
from .index import Clip


def _cache_path(clip: Clip, settings: Settings) -> Path:
    return Path(settings.cache_dir) / "parsed" / clip.dataset / f"{clip.name}.npz"


def _stamp(path: Path) -> np.ndarray:
    st = path.stat()
    return np.array([st.st_size, st.st_mtime_ns], dtype=np.int64)


def _parse_to_cache(path: Path, cache: Path) -> None:
    text = path.read_text(encoding="utf-8")
    parsed = bvhio.parse(text, str(path))
    header = text[: text.index("MOTION")]
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, header=np.array(header), motion=parsed.motion.astype(np.float32),
             frame_time=np.array(parsed.frame_time), stamp=_stamp(path))
    os.replace(tmp, cache)


def _is_fresh(clip: Clip, cache: Path) -> bool:
    if not cache.exists():
        return False
    with np.load(cache) as z:
        return bool(np.array_equal(z["stamp"], _stamp(clip.path)))


def load_bvh(clip: Clip, settings: Settings | None = None) -> bvhio.BvhFile:
    """The clip's BVH (float32 precision), from the cache when it is fresh."""
    settings = settings or get_settings()
    cache = _cache_path(clip, settings)
    if not _is_fresh(clip, cache):
        _parse_to_cache(clip.path, cache)
    with np.load(cache) as z:
        header = str(z["header"])
        skeleton_only = bvhio.parse(f"{header}MOTION\nFrames: 0\nFrame Time: {float(z['frame_time'])!r}\n", str(clip.path))
        return bvhio.BvhFile(skeleton_only.joints, float(z["frame_time"]), z["motion"].astype(np.float64), str(clip.path))


def load_motion(clip: Clip, settings: Settings | None = None) -> Motion:
    return from_bvh(load_bvh(clip, settings))


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
