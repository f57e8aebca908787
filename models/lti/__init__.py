"""LTI style translation (Hsu, Pulli & Popović 2005, "Style translation for human motion").

Streaming (the project interface, `models/interface.py`): `load(weights_dir)` -> `LTIStyleModel`
with `styles()`, `init_state(batch)`, `step_batch(state, FrameBatch, style_weights)`.
Offline: `model.translators[style].translate_motion(motion, timewarp=...)`.
CLI: `python -m models.lti {train, translate, bench, render}`.
"""

from pathlib import Path

from .model import WEIGHTS_DIR, LTIStyleModel, StyleTranslator


def load(weights_dir: Path = WEIGHTS_DIR, core_only: bool = False) -> LTIStyleModel:
    """The committed translators as one streaming model (the service's registry calls this).
    `core_only`: the published system alone (the identified LTI translators, their blend toward
    the input outside the training range, and the foot planter), without the fitted stages after
    it (the rotation prior, the hinge floors, the raised and waving arms): the evaluation's core-alone row."""
    if not core_only:
        return LTIStyleModel(weights_dir=weights_dir)
    from dataclasses import replace

    from ..motion.hinge import HINGE_FILE
    from .raised_arm import FILE as ARMS_FILE

    translators = {}
    for path in sorted(Path(weights_dir).glob("*.npz")):
        if path.name not in (ARMS_FILE, HINGE_FILE):
            t = replace(StyleTranslator.load(path), prior_mean=None, prior_radii=None)
            translators[t.style] = t
    return LTIStyleModel(translators, weights_dir=weights_dir, raised_arms=False, waving_arms=False, hinges=False)


__all__ = ["WEIGHTS_DIR", "LTIStyleModel", "StyleTranslator", "load"]
