"""numba's cache folder is keyed by every kernel source and the modules they import from, so an
edit to a helper in another file (which numba's own cache would miss) starts a fresh folder."""

import os
import subprocess
import sys
from pathlib import Path

from models import numba_cache

KERNEL = "from numba import njit\n\nfrom .helpers import twice\nfrom ..shared import SCALE\n\n\n@njit(cache=True)\ndef f(x):\n    return twice(x) * SCALE\n"


def _tree(root: Path) -> Path:
    models = root / "models"
    (models / "pkg").mkdir(parents=True)
    (root / "pyproject.toml").write_text("")
    (models / "__init__.py").write_text("")
    (models / "pkg" / "__init__.py").write_text("")
    (models / "pkg" / "kernels.py").write_text(KERNEL)
    (models / "pkg" / "helpers.py").write_text(
        "from numba import njit\n\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n"
    )
    (models / "shared.py").write_text("from .deep import BASE\n\nSCALE = BASE\n")
    (models / "deep.py").write_text("BASE = 3\n")
    (models / "unrelated.py").write_text("X = 1\n")
    return models


def test_key_follows_kernels_and_what_they_import(tmp_path):
    models = _tree(tmp_path)
    names = {p.relative_to(models).as_posix() for p in numba_cache.kernel_sources(models)}
    assert names == {"pkg/kernels.py", "pkg/helpers.py", "shared.py", "deep.py"}
    key = numba_cache.cache_key(models)
    assert numba_cache.cache_key(models) == key
    (models / "unrelated.py").write_text("X = 2\n")
    assert numba_cache.cache_key(models) == key
    edits = (
        ("pkg/helpers.py", "2 * x", "3 * x"),
        ("shared.py", "= BASE", "= 2 * BASE"),
        ("deep.py", "= 3", "= 4"),
        ("pkg/kernels.py", "* SCALE", "* SCALE + 1"),
    )
    for name, old, edit in edits:
        path = models / name
        path.write_text(path.read_text().replace(old, edit))
        new = numba_cache.cache_key(models)
        assert new != key, name
        key = new


def test_folder_is_in_the_checkout_unless_the_user_chose_one(tmp_path):
    models = _tree(tmp_path)
    folder = numba_cache.cache_dir({}, models)
    assert folder == tmp_path / ".cache" / "numba" / numba_cache.cache_key(models)
    assert numba_cache.cache_dir({"NUMBA_CACHE_DIR": "/somewhere"}, models) is None
    (tmp_path / "pyproject.toml").unlink()
    assert numba_cache.cache_dir({}, models) is None


def test_old_folders_are_pruned_and_recent_ones_kept(tmp_path):
    current, recent, old = (tmp_path / name for name in ("current", "recent", "old"))
    for folder in (current, recent, old):
        folder.mkdir()
    now = 1_000_000_000.0
    days = 86400.0
    os.utime(current, (now - 30 * days, now - 30 * days))  # the folder in use is kept, however old
    os.utime(recent, (now - days, now - days))
    os.utime(old, (now - (numba_cache.STALE_DAYS + 1) * days, now - (numba_cache.STALE_DAYS + 1) * days))
    numba_cache.prune(current, now)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["current", "recent"]


def test_this_checkout_compiles_into_the_keyed_folder():
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    code = "import models, numba; print(numba.config.CACHE_DIR)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    expect = Path(numba_cache.__file__).resolve().parents[1] / ".cache" / "numba" / numba_cache.cache_key()
    assert out.stdout.strip() == str(expect)
