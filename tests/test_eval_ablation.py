"""The stage ablation (`tools.ablation`) reports, per row, what switching a stage off changes."""

from __future__ import annotations

import copy
import json
from pathlib import Path

from tools.ablation import changes, declared_stages, method_rows, table

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "eval" / "results.json"


def test_each_method_declares_the_stages_its_loader_switches_off():
    from models.lti import STAGES

    assert declared_stages("lti") == STAGES
    assert "output_prior" in declared_stages("erd") and "carriage" in declared_stages("lpn")


def test_switching_a_stage_off_shows_as_the_change_of_each_row():
    """A recorded run's LTI rows against a copy whose dataset-2 plausibility is 10 points lower and
    jitter 0.3 higher: those rows change by exactly that, every other row and metric by nothing."""
    results = json.loads(RESULTS.read_text())
    without = copy.deepcopy(results)
    for row in without["rows"]:
        if row["variant"] == "lti" and row["source"] == "dataset 2":
            row["plausible"]["share"] -= 0.1
            row["jitter_p90"] += 0.3
    delta = changes(method_rows(results, "lti"), method_rows(without, "lti"))
    assert len(delta) == len(method_rows(results, "lti")) > sum(key[0] == "dataset 2" for key in delta) > 0
    for (source, _, _), d in delta.items():
        moved = source == "dataset 2"
        assert abs(d["plausible"] - (-10.0 if moved else 0.0)) < 1e-9
        assert abs(d["jitter"] - (0.3 if moved else 0.0)) < 1e-9
        assert d["style"] == d["pops"] == 0.0
    text = table("raised_arm", delta)
    assert "### without raised_arm" in text and "-10.0" in text and "+0.30" in text
