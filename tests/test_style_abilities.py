"""The optional style abilities each method declares (`models.interface`): which model has which,
a server's own copy of a changeable style set, a style saved to its folder and loaded back, and
the clips a model refuses before any work is spent on them."""

from __future__ import annotations

import numpy as np
import pytest

from models.interface import ClipStyles, StyleRejected, UploadedStyles, own_style_set
from models.lpn.styles import LPNUpload
from models.registry import load_models
from models.settings import get_settings
from tests.lpn_films import film_of


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


def test_each_method_declares_what_it_can_do_with_uploaded_clips(models):
    assert isinstance(models["lti"], UploadedStyles) and not isinstance(models["lti"], ClipStyles)
    assert isinstance(models["lpn"], ClipStyles)
    assert isinstance(models["erd"], ClipStyles)  # a clip gives a branch, code and stages at once
    assert own_style_set(models["erd"]) is not models["erd"]
    assert [m.controllable for m in (models["lti"], models["erd"], models["lpn"])] == [False, False, True]


def test_a_copy_has_a_style_set_of_its_own(models):
    lpn = models["lpn"]
    before = lpn.styles()
    mine = own_style_set(lpn)
    mine.install_style("zz-own", LPNUpload(film_of(lpn, "elderly")))
    mine.remove_style("giant" if "giant" in before else before[-1])
    assert lpn.styles() == before and "zz-own" in mine.styles()
    assert mine.p is lpn.p  # the weights are shared, not copied

    lti = models["lti"]
    theirs = lti.styles()
    own = own_style_set(lti)
    own.remove_style(theirs[-1])
    assert lti.styles() == theirs and own.styles() == theirs[:-1]


def test_a_saved_style_loads_back_the_same(models, tmp_path):
    lpn, lti = models["lpn"], models["lti"]
    assert not lpn.has_saved_style(tmp_path) and not lti.has_saved_style(tmp_path)
    film = film_of(lpn, "elderly")
    lpn.save_style(LPNUpload(film), tmp_path)
    np.testing.assert_array_equal(lpn.load_style("mine", tmp_path).film, film)
    lti.save_style(lti.translators["elderly"], tmp_path)
    back = lti.load_style("mine", tmp_path)
    assert back.style == "mine" and lti.has_saved_style(tmp_path) and lpn.has_saved_style(tmp_path)
    np.testing.assert_array_equal(back.A, lti.translators["elderly"].A)
    assert lti.style_file("elderly") is not None and lti.style_file("elderly").exists()
    assert lpn.style_file("elderly") is None


def test_clips_a_model_cannot_use_are_refused_before_any_work(models):
    with pytest.raises(StyleRejected) as lti:
        models["lti"].check_upload(300, fine_tune=False)
    assert lti.value.code == "fine_tune_required" and not lti.value.unavailable
    models["lpn"].check_upload(60, fine_tune=False)  # a clip embedding needs no held-back frames
    with pytest.raises(StyleRejected) as lpn:
        models["lpn"].check_upload(60, fine_tune=True)
    assert lpn.value.code == "bad_length" and "fine-tuning needs at least" in lpn.value.message
