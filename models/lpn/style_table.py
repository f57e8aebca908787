"""What LPN-FiLM keeps per style: one row per style in one immutable table, replaced whole on
every change, so a step reads FiLM vectors, balls and carriage of one and the same style set.
Rows measured on a style's real clips describe that style only: a style added at run time, or
given another FiLM vector, gets the plain row.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np


def _identity(shape: tuple[int, ...]) -> np.ndarray:
    return np.broadcast_to(np.array((0.0, 0.0, 0.0, 1.0)), shape).copy()


# measured per-style arrays, and the row of a style nothing was measured for (given its shape)
PLAIN: dict[str, Callable[[tuple[int, ...]], np.ndarray]] = {
    "ball_mean": _identity,  # (J, 4) the ball's centre: any, with an infinite radius
    "ball_radii": lambda shape: np.full(shape, np.inf),  # (2, J): no clamp
    "arms": _identity,  # (A, 4) arm offsets: none
    # the output prior (`output_prior.py`): source and style means (J, 4), maps (J, 3, 3), radii (J,), on (): off
    "prior_source": _identity,
    "prior_mean": _identity,
    "prior_map": lambda shape: np.broadcast_to(np.eye(3), shape).copy(),
    "prior_radius": lambda shape: np.full(shape, np.inf),
    # the run prior's rows, the same as the walk prior's for a style fitted once
    "prior_run_source": _identity,
    "prior_run_mean": _identity,
    "prior_run_map": lambda shape: np.broadcast_to(np.eye(3), shape).copy(),
    "prior_run_radius": lambda shape: np.full(shape, np.inf),
    "prior_on": np.zeros,
    # the arm coupling (`arm_coupling.py`): real means (J, 4), walk and run gains (L, 3D + 1, 3), on (): off
    "couple_mean": _identity,
    "couple_walk": np.zeros,
    "couple_run": np.zeros,
    "couple_on": np.zeros,
}


@dataclass(frozen=True)
class StyleTable:
    names: tuple[str, ...]
    films: np.ndarray  # (S, 4H) FiLM vectors
    measured: dict[str, np.ndarray] = field(default_factory=dict)  # key of PLAIN -> (S, ...)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def get(self, key: str) -> np.ndarray | None:
        return self.measured.get(key)

    def measuring(self, **arrays: np.ndarray | None) -> StyleTable:
        """This table with measured arrays (rows aligned with `names`) set, or dropped where None."""
        measured = {k: v for k, v in self.measured.items() if k not in arrays}
        for key, rows in arrays.items():
            if key not in PLAIN:
                raise KeyError(f"not a per-style measurement: {key!r}")
            if rows is not None:
                if len(rows) != len(self.names):
                    raise ValueError(f"{key} has {len(rows)} rows for {len(self.names)} styles")
                measured[key] = rows
        return replace(self, measured=measured)

    def with_film(self, name: str, film: np.ndarray) -> StyleTable:
        """`name` with FiLM vector `film` (4H,), added if new; its measured rows become plain."""
        row = np.asarray(film, self.films.dtype).reshape(1, -1)
        if name not in self.names:
            return StyleTable(
                (*self.names, name),
                np.concatenate([self.films, row]),
                {k: np.concatenate([v, PLAIN[k](v.shape[1:])[None]]) for k, v in self.measured.items()},
            )
        k, films = self.index(name), self.films.copy()
        films[k] = row[0]
        measured = {key: v.copy() for key, v in self.measured.items()}
        for key, v in measured.items():
            v[k] = PLAIN[key](v.shape[1:])
        return StyleTable(self.names, films, measured)

    def without(self, name: str) -> StyleTable:
        k = self.index(name)
        return StyleTable(
            self.names[:k] + self.names[k + 1 :],
            np.delete(self.films, k, axis=0),
            {key: np.delete(v, k, axis=0) for key, v in self.measured.items()},
        )
