"""Style-ERD (Tao, Zhan, Chen & van de Panne, CVPR 2022): online motion style transfer with an
encoder-recurrent-decoder network, trained on Bandai Namco dataset 2. `load(weights_dir)` returns
the streaming model (runtime.ERDModel) that the service's registry offers as method "erd"."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .runtime import ERDModel


def load(weights_dir: Path, core_only: bool = False) -> ERDModel:
    """The committed model; `core_only`: the published core alone (`runtime.load`)."""
    from .runtime import load as _load

    return _load(Path(weights_dir), core_only=core_only)
