"""LPN-FiLM (Mason, Starke & Komura 2022): real-time style modelling of locomotion with local motion
phases and FiLM style modulation, trained on Bandai Namco locomotion. `load(weights_dir)` returns
the streaming model (runtime.LPNModel); `python -m models.lpn --help`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .runtime import LPNModel


def load(weights_dir: Path, core_only: bool = False) -> LPNModel:
    """The committed model; `core_only`: the published core alone (`runtime.load`)."""
    from .runtime import load as _load

    return _load(Path(weights_dir), core_only=core_only)


__all__ = ["load"]
