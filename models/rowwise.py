"""Matrix products whose rows do not depend on the batch they are computed in.

The service promises each session the same bits whoever shares its batch, but BLAS picks kernels
by row count. Per product shape: torch (MKL) with rows padded to `QUANTUM` (full speed), or numpy
in fixed 8-row blocks (small products, or where `_rows_agree` finds torch does not hold).
LTI needs none of this (its kernels are per row).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np
import torch

log = logging.getLogger(__name__)

QUANTUM = 4  # torch path: rows padded to a multiple of this
BLOCK = 8  # numpy path: rows go through BLAS in blocks of exactly this
TORCH_MIN_WEIGHTS = 1 << 18  # weights in one product (per stacked matrix) from which torch is used
CHECKED_ROWS = (4, 8, 12, 16, 20, 24, 28, 32, 40, 48, 64, 100, 128, 200, 256, 512)

_verdicts: dict[tuple, bool] = {}
_lock = threading.RLock()  # re-entered: the bfloat16 check times the float32 product


def matmul_rows(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """`x @ w` (leading axes broadcast), each row bit for bit what it is in a batch of any size."""
    if w.shape[-2] * w.shape[-1] >= TORCH_MIN_WEIGHTS and torch_rows_hold(x.shape[:-2], w.shape, x.dtype):
        return _torch_rows(x, w)
    return _blocked_rows(x, w)


def torch_rows_hold(lead: tuple[int, ...], w_shape: tuple[int, ...], dtype: np.dtype) -> bool:
    """Whether the padded torch product keeps rows batch-independent here (checked once per shape)."""
    key = (tuple(lead), tuple(w_shape), np.dtype(dtype).str, torch.get_num_threads())
    verdict = _verdicts.get(key)
    if verdict is None:
        with _lock:
            verdict = _verdicts.get(key)
            if verdict is None:
                verdict = _verdicts[key] = _rows_agree(key[0], key[1], np.dtype(dtype))
                if not verdict:
                    log.warning("torch products depend on the batch for %s @ %s: 8-row numpy blocks", lead, w_shape)
    return verdict


def _rows_agree(lead: tuple[int, ...], w_shape: tuple[int, ...], dtype: np.dtype) -> bool:
    rng = np.random.default_rng(0)
    w = rng.standard_normal(w_shape).astype(dtype)
    x = rng.standard_normal((*lead, max(CHECKED_ROWS) + QUANTUM, w_shape[-2])).astype(dtype)
    return _rows_independent(lambda a: _torch_rows(a, w), x, CHECKED_ROWS[:-1])


def _rows_independent(product: Callable[[np.ndarray], np.ndarray], x: np.ndarray, counts: tuple[int, ...]) -> bool:
    """Whether `product` gives rows the same bits in every batch size of `counts`, and shifted."""
    full = product(x[..., : max(CHECKED_ROWS), :])
    for rows in counts:
        if not np.array_equal(product(x[..., :rows, :]), full[..., :rows, :]):
            return False
    odd = 2 * QUANTUM + 1
    shifted = product(x[..., 3 : 3 + odd, :])  # the same rows at other places in a batch
    return bool(np.array_equal(shifted, full[..., 3 : 3 + odd, :]))


def _padded(x: np.ndarray) -> np.ndarray:
    """x with zero rows added up to a multiple of QUANTUM (at least QUANTUM rows)."""
    rows, inner = x.shape[-2], x.shape[-1]
    padded_rows = max(QUANTUM, -(-rows // QUANTUM) * QUANTUM)
    if padded_rows == rows:
        return np.ascontiguousarray(x)
    padded = np.zeros((*x.shape[:-2], padded_rows, inner), x.dtype)
    padded[..., :rows, :] = x
    return padded


def _torch_rows(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    out = torch.matmul(torch.from_numpy(_padded(x)), torch.from_numpy(np.ascontiguousarray(w))).numpy()
    return out[..., : x.shape[-2], :]


class Bfloat16Product:
    """`x @ w` in bfloat16 summed in float32 (oneDNN), rows padded like the torch path: ~4x faster for
    LPN-FiLM's experts where native (see its model card). Chosen by CPU features, never timing: a
    timed verdict would differ between replicas, and a resumed session would not go on the same."""

    def __init__(self, w: np.ndarray) -> None:
        self.w = torch.from_numpy(np.ascontiguousarray(w, np.float32)).to(torch.bfloat16)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        xt = torch.from_numpy(_padded(np.asarray(x, np.float32))).to(torch.bfloat16)
        return torch.matmul(xt, self.w)[: x.shape[-2]].float().numpy()

    @classmethod
    def for_weights(cls, w: np.ndarray) -> Bfloat16Product | None:
        key = ("bfloat16", tuple(w.shape), torch.get_num_threads())
        with _lock:
            verdict = _verdicts.get(key)
            if verdict is None:
                verdict = _verdicts[key] = native_bfloat16() and cls._rows_hold(w.shape)
                log.info("bfloat16 products for %s: %s", w.shape, "used" if verdict else "not used")
        return cls(w) if verdict else None

    @classmethod
    def _rows_hold(cls, w_shape: tuple[int, ...]) -> bool:
        rng = np.random.default_rng(0)
        product = cls(rng.standard_normal(w_shape).astype(np.float32))
        x = rng.standard_normal((max(CHECKED_ROWS) + QUANTUM, w_shape[-2])).astype(np.float32)
        return _rows_independent(product, x, (1, 2, 3, *CHECKED_ROWS[:-1]))


def native_bfloat16() -> bool:
    """Whether this CPU has native bfloat16 (AVX512-BF16 or AMX) as oneDNN sees it; emulated is slower."""
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in probes)


def _blocked_rows(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    rows, inner = x.shape[-2], x.shape[-1]
    blocks = -(-rows // BLOCK)
    if rows % BLOCK:
        padded = np.zeros((*x.shape[:-2], blocks * BLOCK, inner), x.dtype)
        padded[..., :rows, :] = x
    else:
        padded = np.ascontiguousarray(x)
    out = np.matmul(padded.reshape(*x.shape[:-2], blocks, BLOCK, inner), w[..., None, :, :])
    return out.reshape(*out.shape[:-3], blocks * BLOCK, out.shape[-1])[..., :rows, :]
