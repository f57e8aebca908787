"""numba's kernels, as this checkout compiled them, carried into the image build.

    python3 docker/numba_seed.py stage docker/numba-seed     # on the host (docker/build-image.sh)
    python docker/numba_seed.py seed /seed "$NUMBA_CACHE_DIR"  # in the image, before its warm-up

numba names a kernel's cache folder after the absolute path of its source's folder
(`<folder name>_<sha1 of the path>`), so the checkout's cache (`.cache/numba/<key>/`, see
models/numba_cache.py) is not where the installed package looks for it. `stage` copies it out by
package-relative folder; `seed` puts each folder where numba looks for the installed one. Nothing
here decides whether a kernel is fresh: numba checks each index against the sha256 of its source
file and its own version, and the keyed folder already holds only kernels compiled from the
current `models/` sources, so a kernel whose source differs is compiled again in the image as
before. Standard library only: `stage` runs with the host's python3.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import shutil
import sys
from pathlib import Path

REPO = Path(os.path.abspath(__file__)).parents[1]  # as the checkout spells it (numba does not resolve links)
PACKAGES = ("models", "service")  # the packages that define kernels
CACHE_FILES = ("*.nbi", "*.nbc")


def _numba_folder_name(folder: str) -> str:
    """numba's `_CacheLocator.get_suitable_cache_subpath` for a source file in `folder`."""
    return f"{os.path.basename(folder)}_{hashlib.sha1(folder.encode()).hexdigest()}"


def _keyed_cache(repo: Path) -> Path:
    """The checkout's cache folder for its current kernel sources. Whatever NUMBA_CACHE_DIR says
    (the tests' processes set it to this folder; a user's own folder is not keyed by the sources,
    so it could hold a kernel built against an older helper), only this folder is staged."""
    spec = importlib.util.spec_from_file_location("_numba_cache", repo / "models" / "numba_cache.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # (its import-time `configure` only sets this process's env)
    return module.cache_dir({}, repo / "models")


def stage(dest: Path, repo: Path = REPO) -> int:
    """Copy the checkout's cached kernels into `dest/<package-relative folder>/`; how many files."""
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    cache = _keyed_cache(repo)
    if not cache.is_dir():
        return 0
    names: dict[str, Path] = {}
    for package in PACKAGES:
        for folder in [repo / package, *(p for p in (repo / package).rglob("*") if p.is_dir())]:
            rel = folder.relative_to(repo)
            for spelling in {os.path.abspath(folder), os.path.realpath(folder)}:
                names[_numba_folder_name(spelling)] = rel
    copied = 0
    for sub in cache.iterdir():
        rel = names.get(sub.name)
        if rel is None:
            continue
        for pattern in CACHE_FILES:
            for file in sub.glob(pattern):
                (dest / rel).mkdir(parents=True, exist_ok=True)
                shutil.copy2(file, dest / rel / file.name)
                copied += 1
    return copied


def seed(src: Path, cache_dir: Path) -> int:
    """Put each staged folder where numba looks for the installed package's; how many files."""
    spec = importlib.util.find_spec("models")  # the installed package, not imported
    assert spec is not None and spec.origin is not None, "models is not installed"
    site = Path(spec.origin).parents[1]
    copied = 0
    for file in sorted(src.rglob("*")):
        if file.is_file():
            target = cache_dir / _numba_folder_name(str(site / file.parent.relative_to(src)))
            target.mkdir(parents=True, exist_ok=True)
            shutil.copy2(file, target / file.name)
            copied += 1
    return copied


if __name__ == "__main__":
    command, *args = sys.argv[1:]
    if command == "stage":
        print(f"numba-seed: staged {stage(Path(args[0]))} cached kernel files")
    elif command == "seed":
        print(f"numba-seed: seeded {seed(Path(args[0]), Path(args[1]))} cached kernel files")
    else:
        sys.exit(f"usage: {sys.argv[0]} stage DEST | seed SRC CACHE_DIR")
