"""Tuning some built-in LPN-FiLM styles (`models.lpn.tune_builtin`) replaces only those styles'
tuned vectors: the others keep what an earlier run gave them, in the file and in its record."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from models.lpn.tune_builtin import StyleResult, TuneConfig, save
from models.lpn.weights import CONFIG_FILE, TUNED_FILE
from models.settings import get_settings


def _committed(tmp_path: Path) -> Path:
    folder = tmp_path / "lpn"
    folder.mkdir()
    for name in (TUNED_FILE, CONFIG_FILE):
        shutil.copy(get_settings().weights_dir / "lpn" / name, folder / name)
    return folder


def _tuned(folder: Path) -> dict[str, np.ndarray]:
    with np.load(folder / TUNED_FILE) as z:
        return {str(s): f for s, f in zip(z["styles"], z["film"])}


def _result(style: str, film: np.ndarray, kept: bool) -> StyleResult:
    return StyleResult(style, film, val_before=0.07, val_after=0.06 if kept else 0.08, lr=0.03, steps=1200)


def test_tuning_one_style_keeps_the_other_styles_tuned_vectors(tmp_path):
    folder = _committed(tmp_path)
    before = _tuned(folder)
    before.pop("exhausted", None)  # tuned in the committed file or not: this run replaces it
    assert len(before) >= 2
    new = np.full_like(next(iter(before.values())), 0.5)

    save(folder, [_result("exhausted", new, kept=True)], TuneConfig(styles="exhausted"), 30.0)

    after = _tuned(folder)
    assert set(after) == set(before) | {"exhausted"}
    np.testing.assert_array_equal(after["exhausted"], new)
    for style, film in before.items():
        np.testing.assert_array_equal(after[style], film)
    committed = json.loads((get_settings().weights_dir / "lpn" / CONFIG_FILE).read_text())["tuned_film"]
    record = json.loads((folder / CONFIG_FILE).read_text())["tuned_film"]
    assert set(record["styles"]) >= set(before) | {"exhausted"}
    assert record["styles"]["exhausted"]["replaced"] is True
    for style in before:  # the earlier runs' records stay, with the command that made them
        assert record["styles"][style] == committed["styles"][style]
    assert record["runs"][:-1] == committed["runs"] and record["runs"][-1]["config"]["styles"] == "exhausted"


def test_a_retuned_style_that_is_not_kept_goes_back_to_its_exported_vector(tmp_path):
    folder = _committed(tmp_path)
    before = _tuned(folder)
    style = next(iter(before))

    save(folder, [_result(style, before[style] + 1.0, kept=False)], TuneConfig(styles=style), 30.0)

    after = _tuned(folder)
    assert set(after) == set(before) - {style}
    record = json.loads((folder / CONFIG_FILE).read_text())["tuned_film"]["styles"]
    assert record[style]["replaced"] is False
