"""Where numba keeps its compiled kernels: a folder keyed by the kernel sources.

numba's on-disk cache (`cache=True`) checks only the file that defines a kernel, not the files it
calls into (numba #1833): a kernel calling `quaternion.qmul` would keep running an old `qmul` after
an edit. So, unless the user set NUMBA_CACHE_DIR, the cache lives in `.cache/numba/<key>/` of the
checkout, where the key hashes every kernel source under `models/` and every `models` module they
import from at module level, directly or not (constants such as joint indices are frozen into
compiled code too). Any edit there starts a fresh folder. `models/__init__.py` imports this
module, so it runs before any kernel module is decorated.
"""

from __future__ import annotations

import ast
import hashlib
import os
import re
import shutil
import sys
import time
from collections.abc import Mapping
from pathlib import Path

MODELS = Path(__file__).resolve().parent
STALE_DAYS = 7  # a keyed folder no process has added to for this long belongs to old sources
_DECORATOR = re.compile(r"^@njit\b", re.MULTILINE)


def _is_kernel(text: str) -> bool:
    return _DECORATOR.search(text) is not None


def _imported_files(path: Path, tree: ast.Module, root: Path) -> set[Path]:
    """The files under `root` that `path` imports from at module level (relative or `models.`
    imports): where the globals a kernel reads come from."""
    found: set[Path] = set()
    for node in tree.body:
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            base = path.parent
            for _ in range(node.level - 1):
                base = base.parent
        elif node.module and node.module.split(".")[0] == root.name:
            base = root.parent
        else:
            continue
        stem = base.joinpath(*node.module.split(".")) if node.module else base
        candidates = [stem.with_suffix(".py"), stem / "__init__.py"]
        candidates += [stem / f"{alias.name}.py" for alias in node.names]
        found.update(c for c in candidates if c.is_file() and c.resolve().is_relative_to(root))
    return found


def kernel_sources(root: Path = MODELS) -> list[Path]:
    """Every file defining a kernel, and every file under `root` those files import from, directly
    or not (a constant a kernel reads may be computed from another module's)."""
    todo = [path for path in root.rglob("*.py") if _is_kernel(path.read_text(encoding="utf-8"))]
    files: set[Path] = set()
    while todo:
        path = todo.pop()
        if path not in files:
            files.add(path)
            todo += _imported_files(path, ast.parse(path.read_text(encoding="utf-8")), root)
    return sorted(files)


def cache_key(root: Path = MODELS) -> str:
    """A short hash of the kernel sources' paths and contents."""
    digest = hashlib.sha256()
    for path in kernel_sources(root):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()[:16]


def cache_dir(environ: Mapping[str, str], root: Path = MODELS) -> Path | None:
    """The folder to use, or None to leave numba's own choice (the user's NUMBA_CACHE_DIR, or an
    installed copy of the package with no checkout around it)."""
    if environ.get("NUMBA_CACHE_DIR") or not (root.parent / "pyproject.toml").is_file():
        return None
    return root.parent / ".cache" / "numba" / cache_key(root)


def prune(folder: Path, now: float | None = None) -> None:
    """Remove the other keyed folders beside `folder` that nothing was added to for `STALE_DAYS`:
    every edit of a kernel source starts a new folder, and the old ones would pile up."""
    cutoff = (time.time() if now is None else now) - STALE_DAYS * 86400
    if not folder.parent.is_dir():
        return
    for old in folder.parent.iterdir():
        if old != folder and old.is_dir() and old.stat().st_mtime < cutoff:
            shutil.rmtree(old, ignore_errors=True)


def configure() -> None:
    """Point numba at the keyed folder. numba reads NUMBA_CACHE_DIR when it is imported and its
    cache locator reads `numba.config.CACHE_DIR` when a kernel is decorated, so both are set."""
    folder = cache_dir(os.environ)
    if folder is None:
        return
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    prune(folder)
    config = sys.modules.get("numba.core.config")
    if config is not None:
        config.CACHE_DIR = str(folder)  # type: ignore[attr-defined]


configure()
