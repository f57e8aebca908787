"""The 100STYLE loader on a small fixture in that layout, built from Bandai Namco files."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from models.data import DataError, build_index, load_motion, select
from models.lpn import features as lf
from models.lpn.dataset import DataConfig, all_styles, clip_samples, gait_of
from models.lpn.hundred_style import clips, load_clip, load_take, read_frame_cuts, scan

HEADER = (
    "STYLE_NAME,BR_START,BR_STOP,BW_START,BW_STOP,FR_START,FR_STOP,FW_START,FW_STOP,ID_START,ID_STOP,"
    "SR_START,SR_STOP,SW_START,SW_STOP,TR1_START,TR1_STOP,TR2_START,TR2_STOP,TR3_START,TR3_STOP"
)


@pytest.fixture(scope="module")
def layout(tmp_path_factory):
    """Neutral (FW, FR) and Old (FW) from dataset 1, in 100STYLE's folders and names."""
    root = tmp_path_factory.mktemp("100style")
    index = build_index(["bandai-namco-1"])
    files = {
        ("Neutral", "FW"): select(index, style="normal", content="walk")[0],
        ("Neutral", "FR"): select(index, style="normal", content="run")[0],
        ("Old", "FW"): select(index, style="old", content="walk")[0],
    }
    for (style, gait), clip in files.items():
        (root / style).mkdir(exist_ok=True)
        shutil.copy(clip.path, root / style / f"{style}_{gait}.bvh")
    na = ["N/A"] * 20
    neutral, old = list(na), list(na)
    neutral[4:8] = ["10", "79", "5", "104"]  # FR 10..79, FW 5..104
    old[6:8] = ["0", "89"]  # FW 0..89
    (root / "Frame_Cuts.csv").write_text(
        "\n".join([HEADER, ",".join(["Neutral", *neutral]), ",".join(["Old", *old])]) + "\n"
    )
    return root, files


def test_frame_cuts_skip_missing_ranges(layout):
    root, _ = layout
    cuts = read_frame_cuts(root)
    assert cuts == {("Neutral", "FR"): (10, 79), ("Neutral", "FW"): (5, 104), ("Old", "FW"): (0, 89)}


def test_scan_and_clips_label_styles_and_gaits(layout):
    root, _ = layout
    assert [(t.style, t.gait) for t in scan(root)] == [("Neutral", "FR"), ("Neutral", "FW"), ("Old", "FW")]
    got = {(c.style, c.content, c.frames) for c in clips(root)}
    assert got == {("normal", "run", 70), ("normal", "walk", 100), ("old", "walk", 90)}
    assert gait_of("run") == 1.0 and gait_of("walk") == 0.0
    assert all_styles(DataConfig(hundred_style_dir=str(root), held_out=())) == ["normal", "old"]


def test_take_is_cut_to_its_range_on_the_model_skeleton(layout):
    root, files = layout
    take = next(t for t in scan(root) if t.gait == "FW" and t.style == "Neutral")
    motion = load_take(take)
    source = load_motion(files[("Neutral", "FW")])
    assert motion.num_frames == 100 and motion.fps == 30.0
    np.testing.assert_allclose(motion.rotations, source.rotations[5:105], atol=1e-6)
    samples = clip_samples(load_clip(next(c for c in clips(root) if c.name == "Neutral_FW")), gait=0.0)
    assert samples.X.shape == (100 - 1 - lf.FUTURE * lf.STEP, lf.X_DIM) and np.isfinite(samples.Y).all()


def test_broken_layouts_raise_clear_errors(layout, tmp_path):
    root, _ = layout
    with pytest.raises(DataError, match="Frame_Cuts.csv"):
        scan(tmp_path)
    shutil.copytree(root, tmp_path / "copy")
    (tmp_path / "copy" / "Old" / "Old_FW.bvh").unlink()
    with pytest.raises(DataError, match="missing"):
        scan(tmp_path / "copy")
    text = (root / "Frame_Cuts.csv").read_text().replace("0,89", "0,99999")
    (tmp_path / "copy" / "Frame_Cuts.csv").write_text(text)
    shutil.copy(root / "Old" / "Old_FW.bvh", tmp_path / "copy" / "Old" / "Old_FW.bvh")
    take = next(t for t in scan(tmp_path / "copy") if t.style == "Old")
    with pytest.raises(DataError, match="beyond"):
        load_take(take)
