"""A smaller copy of a dataset's archive (same layout, only some contents' takes), for a machine
that gets its data as a carried folder: `build_index` on it lists the original's clips of those
contents with the same splits (groups are kept whole).

    python -m models.data subset --dataset bandai-namco-2 --content walk,run --out .data/carry/data   # .data/ is git-ignored
"""

from __future__ import annotations

import tarfile
from pathlib import Path
from typing import Literal

from ..settings import Settings, get_settings
from .archives import DATASETS, archive_file, record_sum, sha256_file

XzPreset = Literal[0, 1, 2, 3, 4, 5, 6, 7, 8, 9]


def take_content(member: str) -> str | None:
    """The content in a take's file name (`dataset-N_{content}_{style}_{take}`), None for no take."""
    name = Path(member).name
    if not name.startswith("dataset-") or not name.endswith((".bvh", ".json")):
        return None
    parts = name.split("_")
    return parts[1] if len(parts) == 4 else None


def write_subset(
    name: str, contents: tuple[str, ...], out_dir: Path, settings: Settings | None = None, preset: XzPreset = 6
) -> Path:
    """Write `out_dir/<archive>` with the takes of `contents` (all if empty), its sum into SHA256SUMS."""
    spec = DATASETS[name]
    if spec.skeleton != "bandai-namco":
        raise ValueError(f"{name}: subsets are made of Bandai Namco archives only (take names carry the content)")
    source = archive_file(name, settings or get_settings())
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / spec.archive
    tmp = target.with_suffix(".partial")
    with tarfile.open(source, "r:xz") as src, tarfile.open(tmp, mode="w:xz", preset=preset) as dst:
        for member in src:
            content = take_content(member.name)
            if content is not None and contents and content not in contents:
                continue
            dst.addfile(member, src.extractfile(member) if member.isfile() else None)
    tmp.replace(target)
    record_sum(out_dir, spec.archive, sha256_file(target))
    return target
