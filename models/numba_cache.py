"""Where numba keeps its compiled kernels: a folder keyed by the kernel sources.

numba's cache (`cache=True`) checks only the file defining a kernel, not the files it calls into
(numba #1833): an edited `quaternion.qmul` would go unseen. So, unless NUMBA_CACHE_DIR is set, the
cache lives in `.cache/numba/<key>/`, the key hashing every kernel source under `models/` and every
`models` module they import at module level (constants are frozen into compiled code too).
`models/__init__.py` imports this module, so it runs before any kernel is decorated.
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
    """The files under `root` that `path` imports from at module level: where a kernel's globals live."""
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
    """Every file defining a kernel, and every file under `root` they import from, transitively."""
    todo = [path for path in root.rglob("*.py") if _is_kernel(path.read_text(encoding="utf-8"))]
    files: set[Path] = set()
    while todo:
        path = todo.pop()
        if path not in files:
            files.add(path)
            todo += _imported_files(path, ast.parse(path.read_text(encoding="utf-8")), root)
    return sorted(files)


def cache_key(root: Path = MODELS) -> str:
    digest = hashlib.sha256()
    for path in kernel_sources(root):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()[:16]


def cache_dir(environ: Mapping[str, str], root: Path = MODELS) -> Path | None:
    """The folder to use, or None for numba's own choice (NUMBA_CACHE_DIR set, or no checkout)."""
    if environ.get("NUMBA_CACHE_DIR") or not (root.parent / "pyproject.toml").is_file():
        return None
    return root.parent / ".cache" / "numba" / cache_key(root)


def prune(folder: Path, now: float | None = None) -> None:
    """Remove sibling keyed folders untouched for `STALE_DAYS` (every kernel edit starts a new one)."""
    cutoff = (time.time() if now is None else now) - STALE_DAYS * 86400
    if not folder.parent.is_dir():
        return
    for old in folder.parent.iterdir():
        if old != folder and old.is_dir() and old.stat().st_mtime < cutoff:
            shutil.rmtree(old, ignore_errors=True)


def configure() -> None:
    """Point numba at the keyed folder (NUMBA_CACHE_DIR and `numba.config.CACHE_DIR`)."""
    folder = cache_dir(os.environ)
    if folder is None:
        return
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    prune(folder)
    config = sys.modules.get("numba.core.config")
    if config is not None:
        config.CACHE_DIR = str(folder)  # type: ignore[attr-defined]


configure()
