"""Locating and unpacking the mocap archives.

`../shared/data` (or `STYLESTREAM_DATA_DIR`) holds `.tar.xz` archives and `SHA256SUMS`. An archive
is checked, then unpacked once into the git-ignored cache; a marker records which archive bytes it
came from, so a changed archive is unpacked again. A data folder holding the unpacked dataset
folder is used in place.
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import json
import os
import shutil
import tarfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..settings import Settings, get_settings


class DataError(RuntimeError):
    """The mocap data is missing or does not match its checksum."""


class DataMissing(DataError):
    """No archive nor unpacked folder here: a fact about the machine (tests needing it skip)."""


# how far a long step has got: (bytes done, bytes in all)
Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class DatasetSpec:
    name: str  # our id, e.g. "bandai-namco-2"
    archive: str  # file name in the data folder
    root: str  # top-level folder inside the archive
    bvh_dir: str  # folder of the BVH files, relative to the unpacked root's parent
    skeleton: str  # "bandai-namco" or "cmu"
    licence: str


DATASETS: dict[str, DatasetSpec] = {
    spec.name: spec
    for spec in (
        DatasetSpec(
            "bandai-namco-1",
            "bandai-namco-1.tar.xz",
            "Bandai-Namco-Research-Motiondataset-1",
            "Bandai-Namco-Research-Motiondataset-1/data",
            "bandai-namco",
            "CC BY-NC 4.0",
        ),
        DatasetSpec(
            "bandai-namco-2",
            "bandai-namco-2.tar.xz",
            "Bandai-Namco-Research-Motiondataset-2",
            "Bandai-Namco-Research-Motiondataset-2/data",
            "bandai-namco",
            "CC BY-NC 4.0",
        ),
        DatasetSpec("xia", "xia.tar.xz", "xia", "xia", "cmu", "research use only; cite Xia et al. 2015"),
        DatasetSpec(
            "cmu",
            "cmu.tar.xz",
            "cmu",
            "cmu",
            "cmu",
            "free for research and commercial use; acknowledge mocap.cs.cmu.edu",
        ),
    )
}


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def _expected_sums(data_dir: Path) -> dict[str, str]:
    sums = data_dir / "SHA256SUMS"
    if not sums.exists():
        return {}
    out = {}
    for line in sums.read_text().splitlines():
        parts = line.split()
        if len(parts) == 2:
            out[parts[1].lstrip("*")] = parts[0]
    return out


def record_sum(data_dir: Path, archive: str, digest: str) -> None:
    """Add (or correct) the archive's line in the folder's SHA256SUMS, written whole."""
    sums = data_dir / "SHA256SUMS"
    lines = [ln for ln in (sums.read_text().splitlines() if sums.exists() else []) if ln.split()[-1:] != [archive]]
    tmp = sums.with_name("SHA256SUMS.partial")
    tmp.write_text("".join(f"{ln}\n" for ln in [*lines, f"{digest}  {archive}"]))
    tmp.rename(sums)


def archive_file(name: str, settings: Settings | None = None) -> Path:
    """The dataset's archive in the data folder (`DataMissing` where this machine has none)."""
    path = Path((settings or get_settings()).data_dir) / DATASETS[name].archive
    if not path.exists():
        raise DataMissing(
            f"dataset {name!r}: no {path} (set STYLESTREAM_DATA_DIR to the folder with the mocap archives)"
        )
    return path


def dataset_dir(name: str, settings: Settings | None = None, progress: Progress | None = None) -> Path:
    """Folder holding the dataset's BVH files, unpacked on first use (`progress` hears how far)."""
    settings = settings or get_settings()
    spec = DATASETS[name]
    data_dir = Path(settings.data_dir)
    in_place = data_dir / spec.bvh_dir
    archive = data_dir / spec.archive
    if not archive.exists():
        if in_place.is_dir():
            return in_place
        raise DataMissing(
            f"dataset {name!r}: neither {archive} nor {in_place} exists "
            f"(set STYLESTREAM_DATA_DIR to the folder with the mocap archives, or `stylestream data fetch --from URL`)"
        )
    unpack_root, ident = _unpack_target(name, settings)
    if _unpacked_from(unpack_root, ident):
        return unpack_root / spec.bvh_dir
    unpack_root.parent.mkdir(parents=True, exist_ok=True)
    # one process unpacks, the others (test workers, server workers on a fresh machine) wait for it
    with open(unpack_root.with_name(unpack_root.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not _unpacked_from(unpack_root, ident):
            _unpack(archive, unpack_root, ident, _expected_sums(data_dir).get(spec.archive), progress)
    return unpack_root / spec.bvh_dir


def is_available(name: str, settings: Settings | None = None) -> bool:
    """Whether the dataset's archive or its unpacked folder is in the data folder (a cheap check)."""
    data_dir, spec = Path((settings or get_settings()).data_dir), DATASETS[name]
    return (data_dir / spec.archive).exists() or (data_dir / spec.bvh_dir).is_dir()


def is_unpacked(name: str, settings: Settings | None = None) -> bool:
    """Whether the dataset's archive has been unpacked into the cache (from these archive bytes)."""
    settings = settings or get_settings()
    if not (Path(settings.data_dir) / DATASETS[name].archive).exists():
        return False
    return _unpacked_from(*_unpack_target(name, settings))


def _unpack_target(name: str, settings: Settings) -> tuple[Path, dict]:
    """Where the dataset's archive is unpacked, and what identifies the archive bytes it came from."""
    archive = Path(settings.data_dir) / DATASETS[name].archive
    stat = archive.stat()
    return Path(settings.cache_dir) / "unpacked" / name, {
        "archive": str(archive.resolve()),
        "size": stat.st_size,
        "mtime_ns": stat.st_mtime_ns,
    }


def _unpacked_from(unpack_root: Path, ident: dict) -> bool:
    """Whether `unpack_root` holds a finished unpack of the archive `ident` describes."""
    marker = unpack_root / ".source.json"
    if not marker.exists():
        return False
    recorded = json.loads(marker.read_text())
    return all(recorded.get(k) == v for k, v in ident.items())


class _Counted(io.FileIO):
    """An archive file telling `progress` the compressed bytes read (counting members would decompress twice)."""

    def __init__(self, path: Path, progress: Progress) -> None:
        super().__init__(path, "rb")
        self.total, self.progress = os.fstat(self.fileno()).st_size, progress

    def read(self, size: int | None = -1) -> bytes:
        block = super().read(size) or b""
        self.progress(self.tell(), self.total)
        return block


def _unpack(archive: Path, unpack_root: Path, ident: dict, expected: str | None, progress: Progress | None) -> None:
    """Check the archive's sum and unpack it into `unpack_root`, atomically."""
    digest = sha256_file(archive)
    if expected is not None and digest != expected:
        raise DataError(f"{archive}: SHA-256 {digest} does not match SHA256SUMS ({expected}); refusing to use it")
    if unpack_root.exists():
        shutil.rmtree(unpack_root)
    tmp = unpack_root.with_name(unpack_root.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    with _Counted(archive, progress) if progress else open(archive, "rb") as raw:
        with tarfile.open(fileobj=raw, mode="r:xz") as tar:
            tar.extractall(tmp, filter="data")
    (tmp / ".source.json").write_text(json.dumps({**ident, "sha256": digest}))
    tmp.rename(unpack_root)  # atomic: a crash mid-unpack never leaves a half folder that looks done


def dataset_root(name: str, settings: Settings | None = None) -> Path:
    """The unpacked top-level folder (with cfg/, LICENSE, PROVENANCE.md)."""
    bvh_dir = dataset_dir(name, settings)
    spec = DATASETS[name]
    depth = len(Path(spec.bvh_dir).parts) - len(Path(spec.root).parts)
    return bvh_dir.parents[depth - 1] if depth > 0 else bvh_dir
