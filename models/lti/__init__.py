"""LTI style translation (Hsu, Pulli & Popović 2005, "Style translation for human motion").

Streaming (the project interface, `models/interface.py`): `load(weights_dir)` -> `LTIStyleModel`
with `styles()`, `init_state(batch)`, `step_batch(state, FrameBatch, style_weights)`.
Offline: `model.translators[style].translate_motion(motion, timewarp=...)`.
CLI: `python -m models.lti {train, translate, bench, render, align-plot, card}`.
"""

from pathlib import Path

from .model import WEIGHTS_DIR, LTIStyleModel, StyleTranslator
from .subspace import StateSpace, stabilize, subspace_id
from .warping import dtw, imw


def load(weights_dir: Path = WEIGHTS_DIR) -> LTIStyleModel:
    """The committed translators as one streaming model (the service's registry calls this)."""
    return LTIStyleModel(weights_dir=weights_dir)


__all__ = [
    "WEIGHTS_DIR",
    "LTIStyleModel",
    "StyleTranslator",
    "StateSpace",
    "stabilize",
    "subspace_id",
    "dtw",
    "imw",
    "load",
]
