"""Per-row arrays with spare capacity, for a crowd's troupe (`service.crowd.Troupe`).

A troupe keeps one row per character in a few dozen arrays (its model state, clocks, held
outputs, style weights). Rebuilt whole on every change, a 16,384-character troupe copied ~130 MB
per partial tick (`put_rows`), per join (concatenation) and per leave (a boolean mask): a
neighbour's frames waited behind each copy. Here each array lives in a buffer with room to grow
(doubling), the rows in use are a view of its head, and

- `append` writes the new rows after the last: the touched rows only, within `reserve` rows (the
  caller's character cap: its pages are the kernel's until written), amortised beyond it (a
  doubling copies every row: 26 MB in one go, ~10 ms of a stalled loop, at 3,584 LTI rows);
- `remove` moves the last rows into the freed places (the touched rows only), so the order of
  the rows left changes: it returns which rows moved where;
- writes into rows (`rows.view(key)[sel] = ...`) are in place.

Spare room costs address space, not memory: a large buffer is an anonymous mapping of its own,
whose pages are the kernel's until written and go back to it with the buffer, no heap trim needed
(numpy's own large arrays ask for huge pages, so under THP `madvise` one row written could take
2 MB of each). A view handed out is valid until the next `append`, `remove` or `replace`. Nothing
else holds these arrays: a step gets its rows gathered (a copy), and snapshots are gathered
copies too.
"""

from __future__ import annotations

import mmap

import numpy as np

MIN_CAPACITY = 16
MAPPED_BYTES = 1 << 20  # buffers from this size are mappings of their own


class Rows:
    """Named arrays sharing their first axis (the rows), each in a buffer with spare room."""

    def __init__(self, reserve: int = 0) -> None:
        self._buf: dict[str, np.ndarray] = {}
        self.n = 0
        self.reserve = reserve  # rows every buffer has room for from the start

    def __len__(self) -> int:
        return self.n

    def __contains__(self, key: str) -> bool:
        return key in self._buf

    def keys(self) -> list[str]:
        return list(self._buf)

    def view(self, key: str) -> np.ndarray:
        """The rows in use of `key`: a view, written through."""
        return self._buf[key][: self.n]

    def replace(self, key: str, value: np.ndarray) -> None:
        """All rows of `key` at once (same row count): copied in where shape and dtype allow, else a
        new buffer (a style added or removed changes a weight array's columns)."""
        if len(value) != self.n:
            raise ValueError(f"{key}: {len(value)} rows given for {self.n}")
        buf = self._buf.get(key)
        if buf is not None and buf.shape[1:] == value.shape[1:] and buf.dtype == value.dtype:
            buf[: self.n] = value
        else:
            self._buf[key] = self._grown(value, max(len(buf) if buf is not None else 0, self.n))

    def drop(self, key: str) -> None:
        self._buf.pop(key, None)

    def append(self, values: dict[str, np.ndarray]) -> None:
        """New rows after the last: `values` gives every key's (its rows, the same count each)."""
        if self.n and set(values) != set(self._buf):
            raise KeyError(f"rows appended with keys {sorted(set(values) ^ set(self._buf))} differing")
        if not self.n:  # the first rows say which arrays there are
            self._buf = {key: buf for key, buf in self._buf.items() if key in values}
        k = len(next(iter(values.values()))) if values else 0
        need = self.n + k
        for key, new in values.items():
            buf = self._buf.get(key)
            if buf is None or buf.shape[1:] != new.shape[1:] or buf.dtype != np.result_type(buf.dtype, new.dtype):
                old = buf[: self.n] if buf is not None else np.empty((0, *new.shape[1:]), new.dtype)
                dtype = np.result_type(old.dtype, new.dtype)
                buf = self._buf[key] = self._grown(old.astype(dtype, copy=False), max(2 * need, self.reserve))
            elif len(buf) < need:
                buf = self._buf[key] = self._grown(buf[: self.n], max(2 * need, 2 * len(buf), self.reserve))
            buf[self.n : need] = new
        self.n = need

    def remove(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Free `rows` (distinct): the last rows still in use move into the freed places below the
        new end. Returns (from, to): the rows that moved, and where they are now."""
        rows = np.asarray(rows, np.int64)
        end = self.n - len(rows)
        holes = np.sort(rows[rows < end])  # freed places the rows kept must fill
        gone = np.zeros(self.n - end, bool)
        gone[rows[rows >= end] - end] = True
        movers = end + np.flatnonzero(~gone)  # rows kept beyond the new end
        for buf in self._buf.values():
            buf[holes] = buf[movers]
        self.n = end
        self._shrink()
        return movers, holes

    def _shrink(self) -> None:
        """Hand memory back once a buffer grown past its reserve is mostly empty (a crowd that
        shrank stays small)."""
        for key, buf in self._buf.items():
            if len(buf) > max(MIN_CAPACITY, self.reserve) and self.n < len(buf) // 4:
                self._buf[key] = self._grown(buf[: self.n], max(2 * self.n, self.reserve))

    @staticmethod
    def _grown(head: np.ndarray, capacity: int) -> np.ndarray:
        shape = (max(capacity, len(head), MIN_CAPACITY), *head.shape[1:])
        size = int(np.prod(shape)) * head.dtype.itemsize
        if size >= MAPPED_BYTES:
            area = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
            out = np.frombuffer(area, head.dtype).reshape(shape)  # the array holds the mapping
        else:
            out = np.empty(shape, head.dtype)
        out[: len(head)] = head
        return out
