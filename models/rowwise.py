"""Matrix products whose rows do not depend on the batch they are computed in.

The service steps many sessions (and a crowd's characters) as one batch, and promises that a
character's output is the same bit for bit whoever else is in the batch. A BLAS product does not
keep that promise: OpenBLAS picks its kernels and its split of the rows by the number of rows, so
row i of `X @ W` differs in the last bits between a batch of 1 and a batch of 64 (measured here:
up to 1e-5 on Style-ERD's and LPN-FiLM's layers). Within one call of a fixed row count the rows
are computed alike, wherever they sit (checked for 8 rows on every layer shape the models use,
`tests/test_rowwise.py`). So the rows go through BLAS in blocks of exactly `BLOCK`, the last one
padded with zeros: each row then meets the same kernel whatever the batch. The price is the
padding for small batches and BLAS's weaker amortisation over 8-row blocks (about 2x on
LPN-FiLM's 2048-wide expert layers at 256 rows); LTI needs none of this (its kernels are per row).
"""

from __future__ import annotations

import numpy as np

BLOCK = 8


def matmul_rows(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """`x @ w` for x (..., B, K) and w (..., K, N) (leading axes broadcast as `np.matmul`), each
    of the B rows computed in an 8-row BLAS call of its own block."""
    rows, inner = x.shape[-2], x.shape[-1]
    blocks = -(-rows // BLOCK)
    if rows % BLOCK:
        padded = np.zeros((*x.shape[:-2], blocks * BLOCK, inner), x.dtype)
        padded[..., :rows, :] = x
    else:
        padded = np.ascontiguousarray(x)
    out = np.matmul(padded.reshape(*x.shape[:-2], blocks, BLOCK, inner), w[..., None, :, :])
    return out.reshape(*out.shape[:-3], blocks * BLOCK, out.shape[-1])[..., :rows, :]
