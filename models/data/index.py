"""Dataset index: one `Clip` per BVH take, labelled from the files' own labels, split
train/validation/test (~80/10/10) by a hash of the take name within each (dataset, style,
content) group: independent of file-system order and random state.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

from ..settings import Settings
from .archives import DATASETS, DataError, dataset_dir, dataset_root

SPLITS = ("train", "val", "test")

# CMU trials carry no labels in their names; these come from PROVENANCE.md (CMU descriptions).
_CMU_LABELS = {
    "01_01": ("neutral", "jump"),
    "131_01": ("michael-jackson", "walk"),
    "131_02": ("michael-jackson", "walk"),
    "131_03": ("michael-jackson", "hop"),
}


@dataclass(frozen=True)
class Clip:
    dataset: str
    name: str  # file stem
    path: Path
    style: str
    content: str
    take: str
    fps: float
    skeleton: str
    frames: int
    split: str = "train"

    @property
    def key(self) -> str:
        return f"{self.dataset}/{self.name}"

    @property
    def seconds(self) -> float:
        return self.frames / self.fps


def read_header_counts(path: Path) -> tuple[int, float]:
    """(frames, fps) from the MOTION header, reading only the start of the file."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16).decode("utf-8", "replace")
    frames = re.search(r"Frames:\s*(\d+)", head)
    frame_time = re.search(r"Frame Time:\s*([0-9.eE+-]+)", head)
    if not frames or not frame_time:
        raise DataError(f"{path}: no Frames:/Frame Time: header in the first 64 KiB")
    fps = 1.0 / float(frame_time.group(1))
    return int(frames.group(1)), float(round(fps)) if abs(fps - round(fps)) < 1e-2 else fps


def _labels(dataset: str, path: Path, cfg: dict[str, list[str]]) -> tuple[str, str, str]:
    stem = path.stem
    if dataset.startswith("bandai-namco"):
        label_file = path.with_suffix(".json")
        parts = stem.split("_")  # dataset-N_{content}_{style}_{take}
        if label_file.exists():
            labels = json.loads(label_file.read_text())
            content = cfg["content"][labels["content"]].split("_", 1)[1]
            style = cfg["style"][labels["style"]].split("_", 1)[1]
        else:
            content, style = parts[1], parts[2]
        return style, content, parts[-1]
    if dataset == "xia":
        style, content, index, take = stem.split("_")  # {style}_{content}_{index}_{take}
        return style, content, f"{index}_{take}"
    style, content = _CMU_LABELS.get(stem, ("unknown", "unknown"))
    return style, content, stem


def _assign_splits(clips: list[Clip]) -> list[Clip]:
    def rank(clip: Clip) -> str:
        return hashlib.sha1(clip.key.encode()).hexdigest()

    groups: dict[tuple[str, str, str], list[Clip]] = defaultdict(list)
    for clip in clips:
        groups[(clip.dataset, clip.style, clip.content)].append(clip)
    out: dict[str, str] = {}
    for members in groups.values():
        members.sort(key=rank)
        if len(members) >= 5:
            n_held = max(1, round(0.1 * len(members)))
            for k, clip in enumerate(members):
                out[clip.key] = "val" if k < n_held else "test" if k < 2 * n_held else "train"
        else:
            for clip in members:
                bucket = int(rank(clip)[:8], 16) % 10
                out[clip.key] = "val" if bucket == 0 else "test" if bucket == 1 else "train"
    return [replace(c, split=out[c.key]) for c in clips]


def build_index(datasets: list[str] | None = None, settings: Settings | None = None) -> list[Clip]:
    """Every BVH clip of the given datasets (default: all four), sorted by key, with splits."""
    clips: list[Clip] = []
    for name in datasets or list(DATASETS):
        spec = DATASETS[name]
        folder = dataset_dir(name, settings)
        cfg: dict[str, list[str]] = {}
        if spec.skeleton == "bandai-namco":
            root = dataset_root(name, settings)
            cfg = {kind: (root / "cfg" / f"{kind}_label.txt").read_text().split() for kind in ("content", "style")}
        for path in sorted(folder.glob("*.bvh")):
            style, content, take = _labels(name, path, cfg)
            frames, fps = read_header_counts(path)
            clips.append(Clip(name, path.stem, path, style, content, take, fps, spec.skeleton, frames))
    return _assign_splits(sorted(clips, key=lambda c: c.key))


def select(clips: list[Clip], **where: str | tuple[str, ...]) -> list[Clip]:
    """Filter by attribute, e.g. select(index, dataset="bandai-namco-2", style=("normal", "elderly"))."""

    def keep(clip: Clip) -> bool:
        for attr, want in where.items():
            value = getattr(clip, attr)
            if (value not in want) if isinstance(want, tuple) else (value != want):
                return False
        return True

    return [c for c in clips if keep(c)]
