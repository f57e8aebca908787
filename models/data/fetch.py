"""`stylestream data fetch`: check each dataset's archive against SHA256SUMS and unpack it into the
cache, once. With `--from URL` a missing archive is downloaded from `URL/<archive>` first and
must match `KNOWN_SHA256` (a mirror cannot hand out other bytes) before it is renamed into place.
"""

from __future__ import annotations

import hashlib
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from ..settings import Settings
from .archives import DATASETS, DataError, Progress, dataset_dir, is_unpacked, record_sum

KNOWN_SHA256 = {
    "bandai-namco-1.tar.xz": "a8232ac0c4ebf29c4645cf5b8e21dabd2fee872e47cc53210708015ddd3a345c",
    "bandai-namco-2.tar.xz": "1f6c5d5189fce8a99854dd289a0db0beeb86c2522408d5675578941595f86beb",
    "cmu.tar.xz": "e945c12fdaa2c7752d7434a805c27ab3b425c8ab3b24f8cc65475785a9b6ad29",
    "xia.tar.xz": "76f2a3b77fe160b6b6dcf69775265ecdf8629bb75a836e157f8a408db02d95be",
}


class ArchivesMissing(DataError):
    """Archives the data folder lacks, with nowhere given to download them from."""

    def __init__(self, archives: list[str], data_dir: Path) -> None:
        super().__init__(
            f"{', '.join(archives)} not in {data_dir}: put the mocap archives there (or point "
            "STYLESTREAM_DATA_DIR / --data-dir at the folder that holds them), or download them with --from URL"
        )
        self.archives, self.data_dir = archives, data_dir


@dataclass(frozen=True)
class Fetched:
    dataset: str
    state: str  # "ready" (unpacked before), "in place" (unpacked in the data folder), "unpacked"
    downloaded: bool
    folder: Path
    files: int
    seconds: float


class ProgressLine:
    """One line per step, `label: 42% 33.1/79.2 MB`: redrawn on a terminal, written once to a pipe."""

    def __init__(self, label: str, stream: TextIO | None = None) -> None:
        self.label, self.stream = label, stream or sys.stderr
        self.live = self.stream.isatty()
        self.shown = 0.0

    def text(self, done: int, total: int) -> str:
        size = f"{done / 1e6:.1f}/{total / 1e6:.1f} MB" if total else f"{done / 1e6:.1f} MB"
        return f"{self.label}: {100 * done / total:3.0f}% {size}" if total else f"{self.label}: {size}"

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if self.live and (now - self.shown >= 0.1 or done == total):
            self.stream.write("\r" + self.text(done, total))
            self.stream.flush()
            self.shown = now

    def end(self, message: str) -> None:
        self.stream.write(("\r\033[K" if self.live else "") + f"{self.label}: {message}\n")
        self.stream.flush()


def _download(url: str, dest: Path, expected: str, progress: Progress, timeout: float) -> None:
    """`url` into `dest`, refused unless its SHA-256 is `expected`; `dest` appears only when whole."""
    import httpx  # a dependency of the SDK, so always there; imported only to download

    partial = dest.with_name(dest.name + ".partial")
    digest = hashlib.sha256()
    try:
        with httpx.stream("GET", url, timeout=timeout, follow_redirects=True) as reply:
            if reply.status_code != 200:
                raise DataError(f"{url}: HTTP {reply.status_code}")
            total, done = int(reply.headers.get("content-length") or 0), 0
            with open(partial, "wb") as out:
                for block in reply.iter_bytes(1 << 20):
                    out.write(block)
                    digest.update(block)
                    done += len(block)
                    progress(done, total)
    except httpx.HTTPError as exc:
        partial.unlink(missing_ok=True)
        raise DataError(f"{url}: {exc or type(exc).__name__}") from None
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    if digest.hexdigest() != expected:
        partial.unlink()
        raise DataError(f"{url}: SHA-256 {digest.hexdigest()} is not the known {expected}; refusing it")
    partial.rename(dest)


def fetch(
    names: list[str] | None,
    settings: Settings,
    source: str | None = None,
    known: dict[str, str] = KNOWN_SHA256,
    line: Callable[[str], ProgressLine] = ProgressLine,
    timeout: float = 60.0,
) -> list[Fetched]:
    """Download what the data folder lacks, unpack every dataset of `names` not yet unpacked."""
    data_dir = Path(settings.data_dir)
    names = names or list(DATASETS)
    absent = [
        DATASETS[n].archive
        for n in names
        if not (data_dir / DATASETS[n].archive).exists() and not (data_dir / DATASETS[n].bvh_dir).is_dir()
    ]
    if absent and source is None:
        raise ArchivesMissing(absent, data_dir)
    if absent:
        unknown = [a for a in absent if a not in known]
        if unknown:
            raise DataError(f"no known SHA-256 for {', '.join(unknown)}: refusing to download unchecked bytes")
        data_dir.mkdir(parents=True, exist_ok=True)
        if not os.access(data_dir, os.W_OK):
            raise DataError(f"{data_dir} is not writable: point STYLESTREAM_DATA_DIR or --data-dir at a folder you own")
    done = []
    for name in names:
        spec, started = DATASETS[name], time.perf_counter()
        archive = data_dir / spec.archive
        downloaded = spec.archive in absent
        if downloaded:
            assert source is not None
            progress = line(f"{name} (download)")
            _download(f"{source.rstrip('/')}/{spec.archive}", archive, known[spec.archive], progress, timeout)
            record_sum(data_dir, spec.archive, known[spec.archive])
            progress.end(f"{archive.stat().st_size / 1e6:.1f} MB, SHA-256 checked")
        if not archive.exists():
            state = "in place"
        elif is_unpacked(name, settings):
            state = "ready"
        else:
            state = "unpacked"
        progress = line(name)
        folder = dataset_dir(name, settings, progress if state == "unpacked" else None)
        files = sum(1 for _ in folder.glob("*.bvh"))
        seconds = time.perf_counter() - started
        progress.end(
            {
                "ready": f"ready, unpacked before: {files} BVH files in {folder}",
                "in place": f"ready, unpacked in the data folder: {files} BVH files in {folder}",
                "unpacked": f"unpacked {files} BVH files into {folder} in {seconds:.1f} s",
            }[state]
        )
        done.append(Fetched(name, state, downloaded, folder, files, seconds))
    return done
