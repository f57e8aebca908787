import numpy as np
import pytest

from models.data import DATASETS, warm_cache
from models.motion import bvh
from models.settings import Settings


def test_a_sample_of_every_dataset_parses_cold_into_a_fresh_cache(index, tmp_path):
    """The first ten files of each dataset and every 50th after them parse into an empty cache,
    which then serves them without parsing again (`test_every_file_parses_cold`, slow, reads all)."""
    settings = Settings(cache_dir=tmp_path)
    sample = [c for d in DATASETS for i, c in enumerate(c for c in index if c.dataset == d) if i < 10 or i % 50 == 0]
    assert {c.dataset for c in sample} == set(DATASETS)
    assert warm_cache(sample, settings) == len(sample)
    assert warm_cache(sample, settings) == 0  # now cached


@pytest.mark.slow
def test_every_file_parses_cold(index, tmp_path):
    """All ~3.1k files of the four datasets parse into a fresh cache (about 45 s on two cores)."""
    settings = Settings(cache_dir=tmp_path)
    assert warm_cache(index, settings) == len(index) == 174 + 2902 + 9 + 4
    assert warm_cache(index, settings) == 0  # now cached


@pytest.mark.parametrize("dataset", list(DATASETS))
def test_round_trip_reproduces_printed_numbers(index, dataset):
    clip = next(c for c in index if c.dataset == dataset)
    original = bvh.read(clip.path)
    again = bvh.parse(bvh.dumps(original))
    assert again.names == original.names
    assert [j.channels for j in again.joints] == [j.channels for j in original.joints]
    np.testing.assert_array_equal(again.motion, original.motion)
    assert again.frame_time == pytest.approx(original.frame_time, rel=1e-6)
    for a, b in zip(again.joints, original.joints):
        np.testing.assert_allclose(a.offset, b.offset, rtol=1e-5, atol=1e-5)


def test_channel_orders_per_dataset(index):
    bn = bvh.read(next(c for c in index if c.dataset == "bandai-namco-1").path)
    assert all(
        j.channels == ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"] for j in bn.joints
    )
    cmu = bvh.read(next(c for c in index if c.dataset == "cmu").path)
    assert cmu.joints[0].channels[3:] == ["Zrotation", "Yrotation", "Xrotation"]
    assert all(len(j.channels) == 3 for j in cmu.joints[1:])
    assert sum(j.end_site is not None for j in cmu.joints) >= 5


def test_crlf_and_tabs_parse_identically(index):
    clip = next(c for c in index if c.dataset == "xia")
    text = clip.path.read_text()
    windows = text.replace("\n", "\r\n").replace(" ", "\t")
    np.testing.assert_array_equal(bvh.parse(windows).motion, bvh.parse(text).motion)


@pytest.mark.parametrize(
    "mutate, line_hint, words",
    [
        (lambda t: t.replace("OFFSET", "OFSET", 1), "OFSET", "unexpected token"),
        (lambda t: t.replace("CHANNELS 6", "CHANNELS 7", 1), "CHANNELS 7", "count"),
        (lambda t: t.replace("Xrotation", "Wrotation", 1), "Wrotation", "unknown channel"),
    ],
)
def test_malformed_header_names_file_and_line(index, mutate, line_hint, words):
    clip = next(c for c in index if c.dataset == "bandai-namco-1")
    text = mutate(clip.path.read_text())
    expected_line = next(i + 1 for i, l in enumerate(text.splitlines()) if line_hint in l)
    with pytest.raises(bvh.BvhError) as err:
        bvh.parse(text, "broken.bvh")
    assert err.value.line == expected_line and err.value.source == "broken.bvh"
    assert words in str(err.value) and str(err.value).startswith(f"broken.bvh:{expected_line}:")


def test_malformed_motion_row_names_its_line(index):
    clip = next(c for c in index if c.dataset == "cmu")
    lines = clip.path.read_text().splitlines()
    first_row = next(i for i, l in enumerate(lines) if l.startswith("Frame Time")) + 1
    bad = lines.copy()
    bad[first_row + 10] = bad[first_row + 10].replace(" ", " abc ", 1)
    with pytest.raises(bvh.BvhError, match=rf":{first_row + 11}: expected 96 values"):
        bvh.parse("\n".join(bad))
    bad = lines.copy()
    bad[first_row + 3] = bad[first_row + 3].rsplit(" ", 1)[0] + " 1.2.3"
    with pytest.raises(bvh.BvhError, match=rf":{first_row + 4}: not a number: '1.2.3'"):
        bvh.parse("\n".join(bad))
    with pytest.raises(bvh.BvhError, match="header says"):
        bvh.parse("\n".join(lines[:-5]))


def test_truncated_hierarchy_is_an_error():
    with pytest.raises(bvh.BvhError, match="no MOTION"):
        bvh.parse("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n")
