"""Matrix products whose rows do not depend on the batch they are computed in.

The service steps many sessions as one batch and promises each character the same output bit for
bit whoever else is in it. BLAS alone does not keep that promise: it picks kernels and row splits
by the row count, so row i of `X @ W` differs in the last bits between batches of 1 and 64.

Two ways keep it; which one is fixed per product shape (never per batch, which is the point):

- **torch (MKL), rows padded to a multiple of `QUANTUM`**: with one thread every row count of 4
  and up gives each row the same bits, with two threads the multiples of 4 do; full BLAS speed
  for large batches.
- **numpy in fixed 8-row blocks**: every row meets the same kernel whatever the batch, at the
  cost of weaker amortisation. Products under `TORCH_MIN_WEIGHTS` weights take this path, where
  torch's per-call overhead would cost more than it saves.

A library, CPU or thread count where the first does not hold is caught by `_rows_agree` before
any output depends on it, and falls back to the second; `tests/test_rowwise.py` checks both and
every model's step. LTI needs none of this (its kernels are per row).
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
    """`x @ w` for x (..., B, K) and w (..., K, N) (leading axes broadcast as `np.matmul`), each of
    the B rows bit for bit what it would be in a batch of any other size."""
    if w.shape[-2] * w.shape[-1] >= TORCH_MIN_WEIGHTS and torch_rows_hold(x.shape[:-2], w.shape, x.dtype):
        return _torch_rows(x, w)
    return _blocked_rows(x, w)


def torch_rows_hold(lead: tuple[int, ...], w_shape: tuple[int, ...], dtype: np.dtype) -> bool:
    """Whether the padded torch product keeps rows independent of the batch for this shape at the
    current torch thread count (checked once per shape and thread count, on random data: which
    kernel runs depends on the shapes, not the values)."""
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
    """Whether `product` gives the first rows of `x` the same bits in batches of every size in
    `counts` as in one of max(CHECKED_ROWS) rows, and rows at a shifted place in a batch too."""
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
    """`x @ w` with x and w rounded to bfloat16 and summed in float32 (oneDNN), rows padded to
    `QUANTUM` like the torch path above. Where the CPU multiplies bfloat16 natively (AVX512-BF16,
    AMX) the expert layers of LPN-FiLM run ~4x faster than in float32 (0.4 % rounding of inputs and
    weights; its model card has what that does to its output). `for_weights` returns one only where
    this machine has native bfloat16 and keeps the rows independent of the batch.

    The choice reads the CPU's features, never a timing: on a loaded machine a timed verdict flips
    from process to process, so two replicas of one service would compute the same session
    differently and a session resumed on the other one would not go on as it would have."""

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
    """Whether this CPU multiplies bfloat16 in hardware (AVX512-BF16 or AMX tiles), as torch's
    oneDNN sees it: there bfloat16 products ran 2.4-8x faster than float32 at 256 rows; emulated,
    they are slower."""
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
