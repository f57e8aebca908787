"""Discovery of the trained models that ship with the project.

Each method package exposes `load(weights_dir) -> StreamingModel` and a `WEIGHTS_SUBDIR`; a
method whose weights are not committed yet is simply not offered."""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

from .interface import StreamingModel

METHODS = ("lti", "erd", "lpn")
log = logging.getLogger(__name__)


def load_models(weights_dir: Path, core_only: bool = False) -> dict[str, StreamingModel]:
    """Every committed method; `core_only`: each one's published core alone, without the fitted
    stages after it (what the evaluation's core-alone rows score)."""
    models: dict[str, StreamingModel] = {}
    for method in METHODS:
        try:
            package = importlib.import_module(f"models.{method}")
        except ModuleNotFoundError:
            continue
        loader = getattr(package, "load", None)
        folder = Path(weights_dir) / method
        if loader is None or not folder.is_dir():
            continue
        models[method] = loader(folder, core_only=True) if core_only else loader(folder)
        log.info("loaded model %s with styles %s", method, models[method].styles())
    return models
