"""Confidence intervals for the accuracies the evaluation reports: every share of clips comes with
its count and a 95 % interval, so one clip more or less is read as what it is."""

from __future__ import annotations

import math

Z95 = 1.959963984540054


def wilson(hits: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval: inside [0, 1] and honest at 0 or n hits and small counts."""
    if n == 0:
        return 0.0, 1.0
    p = hits / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    lo, hi = max(0.0, centre - half), min(1.0, centre + half)
    return (0.0 if hits == 0 else lo), (1.0 if hits == n else hi)  # exact ends, not round-off


def share(hits: int, n: int) -> dict:
    """{hits, n, share, lo, hi}: a share of clips with its interval, as the reports store it."""
    lo, hi = wilson(hits, n)
    return {"hits": int(hits), "n": int(n), "share": hits / n if n else 0.0, "lo": lo, "hi": hi}


def shown(s: dict) -> str:
    """'94 % (32/34, 81-98)': the share, its count and its 95 % interval."""
    if not s["n"]:
        return "–"
    return f"{100 * s['share']:.0f}% ({s['hits']}/{s['n']}, {100 * s['lo']:.0f}–{100 * s['hi']:.0f})"


def share_table(header: str, shares: dict[str, dict]) -> list[str]:
    """Markdown rows: one `shown` share per named row, under `header`."""
    return [f"| {header} | accuracy |", "|---|---|", *(f"| {k} | {shown(v)} |" for k, v in shares.items())]
