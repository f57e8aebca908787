"""A row's result never depends on the batch it is computed in: the products (`models.rowwise`)
and every model's step, which the service's batching and crowds rely on for exact replies."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models import rowwise
from models.data import build_index, load_motion, select
from models.interface import FrameBatch, weight_vector
from models.registry import load_models
from models.rowwise import matmul_rows
from models.settings import get_settings
from tests.clips import frame_row

# the layer shapes the models multiply by: Style-ERD's encoder, LSTM and decoder, LPN-FiLM's experts
SHAPES = [(216, 128), (128, 32), (64, 128), (38, 128), (128, 88), (19, 1024), (343, 2048), (256, 2824)]


@pytest.mark.parametrize("inner,outer", SHAPES)
def test_a_row_of_a_product_is_the_same_in_any_batch(inner, outer):
    rng = np.random.default_rng(inner)
    w = rng.standard_normal((inner, outer)).astype(np.float32)
    x = rng.standard_normal((67, inner)).astype(np.float32)
    alone = np.stack([matmul_rows(x[i : i + 1], w)[0] for i in range(len(x))])
    for batch in (2, 7, 8, 13, 67):
        assert np.array_equal(matmul_rows(x[:batch], w), alone[:batch]), batch
    np.testing.assert_allclose(alone, x @ w, rtol=1e-5, atol=1e-4)  # and it is the product
    # stacked weights (Style-ERD's branches) broadcast as np.matmul does
    stacked = matmul_rows(np.stack([x[:13], x[1:14]]), np.stack([w, w]))
    assert np.array_equal(stacked[1, 0], alone[1])


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("inner,outer", SHAPES[-2:])
def test_padded_torch_products_keep_rows_apart_at_any_thread_count(inner, outer, threads):
    """The torch path LPN-FiLM's expert layers take; where the first-use check finds it does not
    hold, the product falls back to 8-row blocks (checked above), so exactness never depends on it."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        if not rowwise.torch_rows_hold((), (inner, outer), np.dtype(np.float32)):
            pytest.skip(f"this machine's torch depends on the batch at {threads} threads: blocks are used")
        rng = np.random.default_rng(outer)
        w = rng.standard_normal((inner, outer)).astype(np.float32)
        x = rng.standard_normal((300, inner)).astype(np.float32)
        full = rowwise._torch_rows(x, w)
        for batch in (1, 2, 3, 5, 9, 31, 77, 150, 299):
            assert np.array_equal(rowwise._torch_rows(x[:batch], w), full[:batch]), batch
            assert np.array_equal(rowwise._torch_rows(x[batch : batch + 5], w), full[batch : batch + 5]), batch
        assert np.array_equal(matmul_rows(x, w), full)  # the shape is large enough to take this path
    finally:
        torch.set_num_threads(before)


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


@pytest.mark.parametrize("name", ["lti", "erd", "lpn"])
def test_every_model_steps_a_row_as_it_steps_it_alone(models, name):
    model = models[name]
    clips = [load_motion(c) for c in select(build_index(), dataset="bandai-namco-2", style="normal", split="val")[:5]]
    styles = model.styles()
    weights = np.stack([weight_vector(styles, {styles[i % len(styles)]: 1.0}) for i in range(len(clips))])
    together, alone = model.init_state(len(clips)), [model.init_state(1) for _ in clips]
    for t in range(12):
        frames = FrameBatch(np.stack([c.translations[t, 1] for c in clips]), np.stack([c.rotations[t] for c in clips]))
        out, together = model.step_batch(together, frames, weights)
        for i in range(len(clips)):
            single, alone[i] = model.step_batch(alone[i], frame_row(frames, i), weights[i : i + 1])
            assert np.array_equal(single.rotations[0], out.rotations[i]), (t, i)
            assert np.array_equal(single.root[0], out.root[i]), (t, i)


@pytest.mark.parametrize("inner,outer", SHAPES[-2:])
def test_bfloat16_products_keep_rows_apart_and_round_only(inner, outer):
    """LPN-FiLM's expert layers in bfloat16 (`rowwise.Bfloat16Product`), where this machine
    multiplies bfloat16 natively: a row's bits never depend on its batch, and the product is x @ w to
    bfloat16 rounding (8 significant bits of each factor, float32 sums)."""
    rng = np.random.default_rng(inner)
    w = rng.standard_normal((inner, outer)).astype(np.float32)
    product = rowwise.Bfloat16Product.for_weights(w)
    if product is None:
        pytest.skip("no native bfloat16 here (or its rows depend on the batch): float32 is used")
    x = rng.standard_normal((300, inner)).astype(np.float32)
    full = product(x)
    for batch in (1, 2, 3, 5, 9, 31, 77, 150, 299):
        assert np.array_equal(product(x[:batch]), full[:batch]), batch
        assert np.array_equal(product(x[batch : batch + 5]), full[batch : batch + 5]), batch
    exact = x.astype(np.float64) @ w
    assert np.abs(full - exact).max() < 0.02 * np.abs(exact).max()


def test_bfloat16_is_chosen_by_the_cpu_not_by_a_clock(monkeypatch):
    """Replicas of one service must compute a session alike: whether LPN-FiLM's products run in
    bfloat16 follows the CPU's native bfloat16 support (and rows kept apart), not a timing that a
    loaded machine can flip."""
    w = np.random.default_rng(0).standard_normal(SHAPES[-1]).astype(np.float32)
    monkeypatch.setattr(rowwise, "_verdicts", {})
    for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"):
        monkeypatch.setattr(rowwise.torch.cpu, name, lambda: False)
    assert not rowwise.native_bfloat16() and rowwise.Bfloat16Product.for_weights(w) is None
    monkeypatch.setattr(rowwise, "_verdicts", {})
    monkeypatch.setattr(rowwise.torch.cpu, "_is_amx_tile_supported", lambda: True)
    assert rowwise.native_bfloat16()
    assert (rowwise.Bfloat16Product.for_weights(w) is not None) == rowwise.Bfloat16Product._rows_hold(w.shape)
