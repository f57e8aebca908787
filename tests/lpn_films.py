"""What LPN-FiLM tests read of a model's styles (`models/lpn/runtime.py` keeps them in one
`StyleTable` snapshot, `_table`): that snapshot, a style's FiLM vector, and FiLM blended from
style weights."""

from __future__ import annotations

import numpy as np

from models.lpn.runtime import LPNModel
from models.lpn.style_table import StyleTable


def style_table(model: LPNModel) -> StyleTable:
    """Every style's FiLM vector and measured rows (`style_table.py`), as one snapshot."""
    return model._table


def film_of(model: LPNModel, name: str) -> np.ndarray:
    """The (4, H) FiLM vector of a style."""
    table = model._table
    return table.films[table.index(name)].reshape(4, model.H).copy()


def blend_films(model: LPNModel, weights: np.ndarray) -> np.ndarray:
    """(B, S) style weights -> (B, 4, H) FiLM; the weights' shortfall from 1 goes to `normal`."""
    return model._blend(model._table, weights)
