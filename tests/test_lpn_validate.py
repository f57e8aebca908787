"""`python -m models.lpn validate`: candidate weights streamed on the validation split, with the
judge-free pace beside the judges (`models/lpn/validate.py`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from models.lpn.validate import load_reference, misread, pace, validate


def test_pace_is_one_for_the_input_itself_and_zero_for_a_motion_that_stays_put(bn_walk):
    walk = bn_walk.slice(0, 90)
    trans = walk.translations.copy()
    trans[:, 1] = trans[0, 1]  # the hips never leave their first position
    stays_put = replace(walk, translations=trans)
    assert pace([walk], [walk]) == 1.0
    assert pace([stays_put], [walk]) == 0.0


def test_misread_names_what_each_wrong_prediction_was():
    truth = ["run", "run", "walk", "walk-turn-left"]
    predicted = ["walk", "run", "walk-turn-left", "walk-turn-left"]
    assert misread(truth, predicted) == {"run->walk": 1, "walk->walk-turn-left": 1}


def test_the_committed_controller_keeps_up_with_a_validation_walk_toward_elderly(lpn_model, bn_walk):
    """One input, one style: every score is there, and the committed network walks on (the real
    elderly walk is slower than the neutral input, so less than 1, but it does not stand still)."""
    ref = load_reference(("elderly",))
    result = validate(lpn_model, ref, [bn_walk.slice(0, 150)], ["walk"], ("elderly",))["elderly"]
    assert 0.4 < result["pace"] < 1.2
    assert {"style_acc", "style_acc_rot", "content_acc", "rot_within_min", "slide_toe_median"} <= result.keys()
    assert result["content_misread"] == {} or result["content_acc"] == 0.0
    assert np.isfinite(result["fmd"])
