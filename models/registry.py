"""Discovery of the trained models that ship with the project.

Each method package exposes `load(weights_dir) -> StreamingModel`; a method without committed
weights is not offered. A shipped pipeline begins with the posture calibration and ends with the
unseen-content fade where their fitted files exist; a core is the method alone."""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

from .interface import StreamingModel
from .motion.calibration import PostureRange, with_calibration
from .motion.calibration import reference_path as posture_path
from .motion.novelty import NoveltyReference, reference_path
from .motion.novelty_stage import with_novelty

METHODS = ("lti", "erd", "lpn")
log = logging.getLogger(__name__)


def load_models(
    weights_dir: Path, core_only: bool = False, novelty: bool = True, calibration: bool = True
) -> dict[str, StreamingModel]:
    """Every committed method; `core_only`, `novelty`, `calibration` drop stages to compare."""
    models: dict[str, StreamingModel] = {}
    for method in METHODS:
        model = load_model(weights_dir, method, core_only, novelty, calibration)
        if model is not None:
            models[method] = model
            log.info("loaded model %s with styles %s", method, model.styles())
    return models


def load_model(
    weights_dir: Path, method: str, core_only: bool = False, novelty: bool = True, calibration: bool = True
) -> StreamingModel | None:
    """One committed method as `load_models` has it; None where it is not committed."""
    try:
        package = importlib.import_module(f"models.{method}")
    except ModuleNotFoundError:
        return None
    loader = getattr(package, "load", None)
    folder = Path(weights_dir) / method
    if loader is None or not folder.is_dir():
        return None
    if core_only:
        return loader(folder, core_only=True)
    model = loader(folder)
    reference = reference_path(weights_dir, method)
    if novelty and reference.is_file():
        model = with_novelty(model, NoveltyReference.load(reference))
    posture = posture_path(weights_dir, method)
    return with_calibration(model, PostureRange.load(posture)) if calibration and posture.is_file() else model
