"""What LPN-FiLM keeps per style: one row per style in one immutable table, replaced whole on
every change, so a step reads FiLM vectors, stages and their rows of one and the same style set.
Rows fitted on a style's real clips describe that style only: a style added at run time, or
given another FiLM vector, gets rows that change nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..motion.skeleton import Skeleton
from ..stages import Pipeline, Rows


@dataclass(frozen=True)
class StyleTable:
    names: tuple[str, ...]
    films: np.ndarray  # (S, 4H) FiLM vectors
    fitted: tuple[bool, ...]  # per style: the stages' rows are its own (False: rows that change nothing)
    skeleton: Skeleton
    stages: Pipeline = Pipeline()
    rows: dict[str, Rows] = field(init=False)  # per stage that is on, its rows aligned with `names`

    def __post_init__(self) -> None:
        if not (len(self.names) == len(self.films) == len(self.fitted)):
            raise ValueError(f"{len(self.names)} styles, {len(self.films)} FiLM vectors, {len(self.fitted)} flags")
        own = [n if f else None for n, f in zip(self.names, self.fitted)]
        object.__setattr__(self, "rows", self.stages.rows(own, self.skeleton))

    def index(self, name: str) -> int:
        return self.names.index(name)

    def with_stages(self, stages: Pipeline) -> StyleTable:
        return replace(self, stages=stages)

    def with_film(self, name: str, film: np.ndarray) -> StyleTable:
        """`name` with FiLM vector `film` (4H,), added if new; its rows change nothing."""
        row = np.asarray(film, self.films.dtype).reshape(1, -1)
        if name not in self.names:
            return replace(
                self, names=(*self.names, name), films=np.concatenate([self.films, row]), fitted=(*self.fitted, False)
            )
        k, films = self.index(name), self.films.copy()
        films[k] = row[0]
        return replace(self, films=films, fitted=tuple(f and i != k for i, f in enumerate(self.fitted)))

    def without(self, name: str) -> StyleTable:
        k = self.index(name)
        keep = lambda t: t[:k] + t[k + 1 :]  # noqa: E731
        return replace(self, names=keep(self.names), films=np.delete(self.films, k, axis=0), fitted=keep(self.fitted))
