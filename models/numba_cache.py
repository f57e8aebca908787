"""Where numba keeps its compiled kernels: a folder keyed by the kernel sources.

numba's on-disk cache (`cache=True`) checks only the file that defines a kernel, not the files it
calls into (numba #1833): a kernel calling `quaternion.qmul` would keep running an old `qmul` after
an edit. So, unless the user set NUMBA_CACHE_DIR, the cache lives in `.cache/numba/<key>/` of the
checkout, where the key hashes every kernel source under `models/` and every `models` module they
import from (constants such as joint indices are frozen into compiled code too). Any edit there
starts a fresh folder. `models/__init__.py` imports this module, so it runs before any kernel
module is decorated.
"""

from __future__ import annotations

import ast
import hashlib
import os
import sys
from collections.abc import Mapping
from pathlib import Path

MODELS = Path(__file__).resolve().parent


def _is_kernel(text: str) -> bool:
    return "@njit" in text


def _imported_files(path: Path, tree: ast.Module, root: Path) -> set[Path]:
    """The files under `root` that `path` imports from (relative or `models.` imports)."""
    found: set[Path] = set()
    for node in ast.walk(tree):
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
    """Every file defining a kernel, and every file under `root` those files import from."""
    files: set[Path] = set()
    for path in root.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        if _is_kernel(text):
            files.add(path)
            files.update(_imported_files(path, ast.parse(text), root))
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


def configure() -> None:
    """Point numba at the keyed folder. numba reads NUMBA_CACHE_DIR when it is imported and its
    cache locator reads `numba.config.CACHE_DIR` when a kernel is decorated, so both are set."""
    folder = cache_dir(os.environ)
    if folder is None:
        return
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    config = sys.modules.get("numba.core.config")
    if config is not None:
        config.CACHE_DIR = str(folder)  # type: ignore[attr-defined]


configure()
