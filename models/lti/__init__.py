"""LTI style translation (Hsu, Pulli & Popović 2005, "Style translation for human motion").

Streaming (the project interface, `models/interface.py`): `load(weights_dir)` -> `LTIStyleModel`
with `styles()`, `init_state(batch)`, `step_batch(state, FrameBatch, style_weights)`.
Offline: `model.translate(motion, style, timewarp=...)`.
CLI: `python -m models.lti {train, hinges, translate}`.
"""

from pathlib import Path

from .model import STAGES, WEIGHTS_DIR, LTIStyleModel, StyleTranslator


def load(weights_dir: Path = WEIGHTS_DIR, core_only: bool = False) -> LTIStyleModel:
    """The committed translators as one model; `core_only`: the published system alone."""
    from ..settings import get_settings

    off = STAGES if core_only else [n.removeprefix("lti.") for n in get_settings().stages_off if n.startswith("lti.")]
    return LTIStyleModel(weights_dir=weights_dir, off=off)


__all__ = ["STAGES", "WEIGHTS_DIR", "LTIStyleModel", "StyleTranslator", "load"]
