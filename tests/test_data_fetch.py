"""`stylestream data fetch` on a tiny archive the test makes (the committed one-frame CMU rig as
`cmu/01_01.bvh`): the command unpacks it where the settings say, with a progress line, and a
second run does nothing; missing archives are one typed error line; `--from` downloads from a
local HTTP server, refusing bytes whose SHA-256 is not the known one."""

from __future__ import annotations

import functools
import hashlib
import io
import os
import subprocess
import sys
import tarfile
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from models.data import DataError, build_index
from models.data.fetch import ArchivesMissing, ProgressLine, fetch
from models.settings import Settings

REPO = Path(__file__).resolve().parents[1]
RIG = REPO / "models" / "motion" / "assets" / "cmu.bvh"


def tiny_archive(folder: Path) -> tuple[Path, str]:
    """`folder/cmu.tar.xz` holding cmu/01_01.bvh, and its SHA-256."""
    folder.mkdir(parents=True, exist_ok=True)
    archive = folder / "cmu.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(RIG, arcname="cmu/01_01.bvh")
    return archive, hashlib.sha256(archive.read_bytes()).hexdigest()


def run_cli(*args: str, data: Path, cache: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "STYLESTREAM_DATA_DIR": str(data), "STYLESTREAM_CACHE_DIR": str(cache)}
    return subprocess.run(
        [sys.executable, "-m", "clients.cli", "data", *args], cwd=REPO, env=env, capture_output=True, text=True
    )


def test_fetch_unpacks_into_the_configured_cache_once(tmp_path):
    data, cache = tmp_path / "data", tmp_path / "cache"
    _, digest = tiny_archive(data)
    (data / "SHA256SUMS").write_text(f"{digest}  cmu.tar.xz\n")
    first = run_cli("fetch", "--dataset", "cmu", data=data, cache=cache)
    assert first.returncode == 0, first.stderr
    unpacked = cache / "unpacked" / "cmu" / "cmu" / "01_01.bvh"
    assert unpacked.read_bytes() == RIG.read_bytes()
    assert first.stderr.startswith("cmu: unpacked 1 BVH files into") and first.stderr.count("\n") == 1, first.stderr
    marker = cache / "unpacked" / "cmu" / ".source.json"
    stamp = marker.stat().st_mtime_ns
    again = run_cli("fetch", "--dataset", "cmu", data=data, cache=cache)
    assert again.returncode == 0 and "ready, unpacked before: 1 BVH files" in again.stderr, again.stderr
    assert marker.stat().st_mtime_ns == stamp  # not unpacked a second time
    clips = build_index(["cmu"], Settings(data_dir=data, cache_dir=cache))
    assert [(c.name, c.frames) for c in clips] == [("01_01", 1)]


def test_missing_archives_are_one_line_naming_them(tmp_path):
    tiny_archive(tmp_path / "data")  # cmu is there, xia is not
    reply = run_cli("fetch", "--dataset", "cmu", "--dataset", "xia", data=tmp_path / "data", cache=tmp_path / "c")
    assert reply.returncode == 2
    assert reply.stderr.count("\n") == 1 and "Traceback" not in reply.stderr, reply.stderr
    assert "xia.tar.xz not in" in reply.stderr and "cmu.tar.xz" not in reply.stderr
    assert not (tmp_path / "c" / "unpacked" / "cmu").exists()  # checked before anything is unpacked
    other = tmp_path / "elsewhere"
    tiny_archive(other / "mirror")
    flag = run_cli(
        "fetch", "--dataset", "cmu", "--data-dir", str(other / "mirror"), data=tmp_path / "none", cache=other
    )
    assert flag.returncode == 0 and (other / "unpacked" / "cmu" / "cmu" / "01_01.bvh").exists(), flag.stderr


@pytest.fixture
def mirror(tmp_path):
    """A local HTTP server over tmp_path/mirror; yields (base URL, folder)."""
    folder = tmp_path / "mirror"
    folder.mkdir()
    handler = functools.partial(SimpleHTTPRequestHandler, directory=str(folder))
    handler.log_message = lambda *a: None  # type: ignore[method-assign]
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/", folder
    finally:
        server.shutdown()
        thread.join()


def test_download_from_a_mirror_is_checked_and_unpacked(mirror, tmp_path):
    url, folder = mirror
    _, digest = tiny_archive(folder)
    settings = Settings(data_dir=tmp_path / "data", cache_dir=tmp_path / "cache")
    log = io.StringIO()
    [got] = fetch(["cmu"], settings, url, known={"cmu.tar.xz": digest}, line=lambda label: ProgressLine(label, log))
    assert (got.state, got.downloaded, got.files) == ("unpacked", True, 1)
    assert (tmp_path / "data" / "cmu.tar.xz").read_bytes() == (folder / "cmu.tar.xz").read_bytes()
    assert (tmp_path / "data" / "SHA256SUMS").read_text() == f"{digest}  cmu.tar.xz\n"
    lines = log.getvalue().splitlines()
    assert lines[0].startswith("cmu (download): ") and "SHA-256 checked" in lines[0], lines
    [again] = fetch(["cmu"], settings, url, known={"cmu.tar.xz": digest}, line=lambda label: ProgressLine(label, log))
    assert (again.state, again.downloaded) == ("ready", False)

    # a mirror serving other bytes than the known ones, or nothing, is refused and leaves nothing
    other = Settings(data_dir=tmp_path / "data2", cache_dir=tmp_path / "cache2")
    with pytest.raises(DataError, match="is not the known"):
        fetch(["cmu"], other, url, known={"cmu.tar.xz": "0" * 64}, line=lambda label: ProgressLine(label, log))
    with pytest.raises(DataError, match="HTTP 404"):
        fetch(["xia"], other, url, known={"xia.tar.xz": digest}, line=lambda label: ProgressLine(label, log))
    with pytest.raises(DataError, match="no known SHA-256"):
        fetch(["xia"], other, url, known={}, line=lambda label: ProgressLine(label, log))
    assert sorted(p.name for p in (tmp_path / "data2").iterdir()) == []
    with pytest.raises(ArchivesMissing):
        fetch(["cmu"], other, None)


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_line_redraws_on_a_terminal_and_is_one_line_in_a_log():
    tty, log = Terminal(), io.StringIO()
    for stream in (tty, log):
        line = ProgressLine("bandai-namco-2", stream)
        for done in (0, 40_000_000, 79_193_360):
            line(done, 79_193_360)
            line.shown = 0.0  # as if a tenth of a second had passed
        line.end("unpacked 2902 BVH files")
    assert tty.getvalue().split("\r")[1:4] == [
        "bandai-namco-2:   0% 0.0/79.2 MB",
        "bandai-namco-2:  51% 40.0/79.2 MB",
        "bandai-namco-2: 100% 79.2/79.2 MB",
    ]
    assert tty.getvalue().endswith("\r\033[Kbandai-namco-2: unpacked 2902 BVH files\n")
    assert log.getvalue() == "bandai-namco-2: unpacked 2902 BVH files\n"
