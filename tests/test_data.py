import shutil
from collections import Counter

import pytest

from models.data import DataError, build_index, dataset_dir, select
from models.data.__main__ import main
from models.data.archives import archive_file
from models.settings import Settings


def test_index_labels_come_from_the_files(index):
    counts = Counter(c.dataset for c in index)
    assert counts == {"bandai-namco-1": 174, "bandai-namco-2": 2902, "xia": 9, "cmu": 4}
    assert sum(c.frames for c in index if c.dataset == "bandai-namco-2") == 384_931
    assert sum(c.frames for c in index if c.dataset == "bandai-namco-1") == 31_914
    bn2 = select(index, dataset="bandai-namco-2")
    assert {c.style for c in bn2} == {"active", "elderly", "exhausted", "feminine", "masculine", "normal", "youthful"}
    assert len({c.content for c in bn2}) == 10
    assert len({c.style for c in select(index, dataset="bandai-namco-1")}) == 15
    assert {c.fps for c in index if c.skeleton == "cmu"} == {120.0}
    assert {c.fps for c in index if c.skeleton == "bandai-namco"} == {30.0}
    xia = {c.name: c for c in select(index, dataset="xia")}
    assert (xia["sexy_walk_01_001"].style, xia["sexy_walk_01_001"].content) == ("sexy", "walk")


def test_split_is_deterministic_and_take_disjoint(index):
    again = build_index()
    assert [(c.key, c.split) for c in again] == [(c.key, c.split) for c in index]
    by_split = {s: {c.key for c in index if c.split == s} for s in ("train", "val", "test")}
    assert not (by_split["train"] & by_split["val"]) and not (by_split["train"] & by_split["test"])
    assert sum(len(v) for v in by_split.values()) == len(index)
    # every dataset-2 style/content has held-out takes in both validation and test
    for style in {c.style for c in index if c.dataset == "bandai-namco-2"}:
        for content in {c.content for c in index if c.dataset == "bandai-namco-2"}:
            group = select(index, dataset="bandai-namco-2", style=style, content=content)
            assert {c.split for c in group} == {"train", "val", "test"}
    n = len(select(index, dataset="bandai-namco-2"))
    assert 0.08 < len(select(index, dataset="bandai-namco-2", split="val")) / n < 0.12


def test_summary_prints_all_four_datasets(capsys):
    assert main(["summary"]) == 0
    out = capsys.readouterr().out
    for name in ("bandai-namco-1", "bandai-namco-2", "xia", "cmu"):
        assert f"== {name}" in out
    assert "files 2902  frames 384931  minutes 213.9" in out
    assert "elderly" in out and "raise-up-both-hands" in out


def test_archive_with_wrong_checksum_is_refused(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    shutil.copy(archive_file("xia"), data / "xia.tar.xz")
    (data / "SHA256SUMS").write_text("0" * 64 + "  xia.tar.xz\n")
    with pytest.raises(DataError, match="does not match SHA256SUMS"):
        dataset_dir("xia", Settings(data_dir=data, cache_dir=tmp_path / "cache"))


def test_data_dir_may_hold_an_unpacked_copy(tmp_path):
    own = tmp_path / "mine"
    shutil.copytree(dataset_dir("cmu"), own / "cmu")
    settings = Settings(data_dir=own, cache_dir=tmp_path / "cache")
    clips = build_index(["cmu"], settings)
    assert [c.name for c in clips] == ["01_01", "131_01", "131_02", "131_03"]
    assert all(str(c.path).startswith(str(own)) for c in clips)


def test_missing_data_gives_a_clear_error(tmp_path):
    with pytest.raises(DataError, match="STYLESTREAM_DATA_DIR"):
        dataset_dir("cmu", Settings(data_dir=tmp_path, cache_dir=tmp_path / "c"))


def test_a_subset_archive_lists_the_same_clips_and_splits(index, tmp_path):
    """What a GPU lease is carried: only some contents' takes, same clips, same splits, checked sum."""
    from models.data.subset import write_subset

    out = tmp_path / "data"
    main(["subset", "--dataset", "bandai-namco-1", "--content", "walk-back,dash", "--out", str(out), "--preset", "0"])
    subset = build_index(["bandai-namco-1"], Settings(data_dir=out, cache_dir=tmp_path / "cache"))
    original = select(index, dataset="bandai-namco-1", content=("walk-back", "dash"))
    assert len(original) > 20
    assert [(c.key, c.style, c.content, c.split, c.frames) for c in subset] == [
        (c.key, c.style, c.content, c.split, c.frames) for c in original
    ]
    assert (out / "SHA256SUMS").read_text().split()[1] == "bandai-namco-1.tar.xz"
    with pytest.raises(ValueError, match="Bandai Namco archives only"):
        write_subset("xia", ("walk",), out)
