"""The held-out upload ruler (`models.eval.uploads`): its coverage is 0 for the input unchanged and
positive for a real clip of the style, and a style counts as held out only where the method ships
no style trained on it."""

from __future__ import annotations

import numpy as np

from models.data import load_motions, select
from models.eval.style_judge import clip_statistics
from models.eval.uploads import D1, D2, REFERENCE_CONTENTS, fit_ruler, held_out_styles, passes


class Shipping:
    def __init__(self, styles: list[str]) -> None:
        self._styles = styles

    def styles(self) -> list[str]:
        return self._styles


def test_coverage_is_zero_for_the_input_and_positive_for_a_real_clip_of_the_style(index):
    d1 = [c for c in select(index, dataset=D1) if c.content in REFERENCE_CONTENTS and c.style in ("normal", "giant")]
    d2 = [c for c in select(index, dataset=D2, split="train", style="normal") if c.content == "walk"][:4]
    stats = {c.key: clip_statistics(m) for c, m in zip(d1 + d2, load_motions(d1 + d2))}
    ruler = fit_ruler(d1 + d2, stats)
    giant = sorted((c for c in d1 if c.style == "giant"), key=lambda c: c.name)
    upload, *others = load_motions(giant)
    neutral = load_motions([c for c in d1 if c.style == "normal" and c.content == "walk"])
    target = np.mean([ruler.z(m) for m in others], axis=0) - ruler.centre[D1]
    starts = [ruler.z(n) for n in neutral]
    assert all(ruler.coverage(z, z, D1, target) == 0.0 for z in starts)
    assert min(ruler.coverage(ruler.z(upload), z, D1, target) for z in starts) > 0.3


def test_a_style_is_held_out_only_where_no_style_was_trained_on_it():
    assert held_out_styles(Shipping(["active", "elderly"]), ("proud", "giant")) == ["proud", "giant"]
    assert held_out_styles(Shipping(["normal", "d1-happy", "elderly"]), ("happy", "proud")) == ["proud"]


def test_the_report_lists_every_upload_row_and_says_which_pass():
    from models.eval.sealed import _uploads_section

    row = {"style": "giant", "method": "lpn", "variant": "tuned", "copy": {D2: 0.05, D1: 0.76}}
    rows = [
        {
            **row,
            "share_of_copy": {D2: 2.4, D1: 0.33},
            "coverage": {D2: 0.12, D1: 0.25},
            "clips": {D2: 2, D1: 2},
            "passes": False,
            "judged": 0.75,
            "judged_by_source": {D2: 1.0, D1: 0.5},
            "judge_passes": False,
            "copy_judged": True,
            "least_bend": -0.04,
        },
        {"style": "giant", "method": "erd", "variant": "refused", "copy": {D2: 0.05, D1: 0.76}},
    ]
    text = "\n".join(_uploads_section(rows))
    assert (
        "| lpn | tuned | giant | 0.05 / 0.76 | 0.12 (2) | 0.25 (2) | (240%) / 33% | no | 75% (100% / 50%) | no | yes "
        "| -0.0 |" in text
    )
    assert "| erd | refused | giant | 0.05 / 0.76 |" in text
    assert _uploads_section([]) == []


def test_an_upload_is_held_to_its_copy_only_where_the_copy_says_something_from_those_inputs():
    copy = {D2: 0.05, D1: 0.5}  # from dataset 2's neutral walks the clip itself is barely closer
    assert passes({D2: -3.0, D1: 0.8}, copy) is True
    assert passes({D2: 9.0, D1: 0.6}, copy) is False
    assert passes({D2: 0.6, D1: 0.9}, {D2: 0.2, D1: 0.5}) is False
    assert passes({D2: 0.0, D1: 0.0}, {D2: 0.0, D1: 0.05}) is None
