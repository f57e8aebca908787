"""Couple joints the way a style's real clips move them together: a joint moved with the joints
it follows by the style's real linear relation instead of the model's.

Per link, target t following drivers u:  d_t' = d_t + (B_real - B_made)^T [d_u, 1], each d a
rotation vector from the style's real mean, B fitted by least squares on real clips and on the
model's output, per gait. Links apply in order; rows weighing no coupled style are unchanged.
Compiled in `coupling_kernels.py` (numpy reference: `tests/reference/coupling.py`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..interface import State
from ..stages import Rows, StageFrame, Stateless, style_rows
from .rotations import quat_exp, quat_inv, quat_log, quat_mean, quat_mul
from .skeleton import Skeleton

Link = tuple[str, tuple[str, ...]]  # a joint and the joints it follows
GAITS = ("walk", "run")
RCOND = 1e-2  # `regression`'s cut-off, relative to the largest singular value


def link_indices(links: Sequence[Link], names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(targets (L,), drivers (L, D) padded with -1): joint indices of `links` in `names`."""
    names = list(names)
    width = max((len(d) for _, d in links), default=0)
    drivers = np.full((len(links), width), -1, np.int64)
    for k, (_, ds) in enumerate(links):
        drivers[k, : len(ds)] = [names.index(d) for d in ds]
    return np.array([names.index(t) for t, _ in links], np.int64), drivers


def deviations(q: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """(..., K, 3) rotation vectors of rotations (..., K, 4) away from means (K, 4), in each joint's frame."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_log(quat_mul(quat_inv(mean), q))


def design(q: np.ndarray, mean: np.ndarray, drivers: np.ndarray) -> np.ndarray:
    """(N, 3D + 1): the drivers' deviations, flattened (zeros for padding), and a constant."""
    used = drivers >= 0
    d = np.zeros((len(q), len(drivers), 3))
    d[:, used] = deviations(q[:, drivers[used]], mean[drivers[used]])
    return np.concatenate([d.reshape(len(q), -1), np.ones((len(q), 1))], axis=1)


def regression(q: np.ndarray, mean: np.ndarray, target: int, drivers: np.ndarray) -> np.ndarray:
    """(3D + 1, 3) least-squares map, directions under `RCOND` dropped (else huge gains on still axes)."""
    x = design(q, mean, drivers)
    used = np.concatenate([np.repeat(drivers >= 0, 3), [True]])
    out = np.zeros((x.shape[1], 3))
    out[used] = np.linalg.lstsq(x[:, used], deviations(q[:, target], mean[target]), rcond=RCOND)[0]
    return out


def moved(q: np.ndarray, mean: np.ndarray, target: int, drivers: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """(N, 4) the target's rotation in rotations (N, J, 4) moved by one style's link gains (N, 3D + 1, 3)."""
    d = deviations(q[:, target], mean[target]) + np.einsum("ni,nij->nj", design(q, mean, drivers), gains)
    return quat_mul(mean[target], quat_exp(d))


@dataclass(frozen=True)
class Coupling(Stateless):
    """The stage: per coupled style, real means (S, J, 4) and real minus made regressions per gait."""

    styles: tuple[str, ...]
    links: tuple[Link, ...]
    mean: np.ndarray
    walk: np.ndarray
    run: np.ndarray

    def aligned(self, names: Sequence[str | None]) -> dict[str, np.ndarray]:
        """`mean`, `walk`, `run` and `on` (S',) aligned with `names`; uncoupled styles change nothing."""
        identity, zero = np.tile((0.0, 0.0, 0.0, 1.0), (self.mean.shape[1], 1)), np.zeros(self.walk.shape[1:])
        return style_rows(
            self.styles,
            names,
            mean=(self.mean, identity),
            walk=(self.walk, zero),
            run=(self.run, zero),
            on=(np.ones(len(self.styles)), 0.0),
        )

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """`aligned` and the links' joints on `skeleton` (`targets`, `drivers`: `link_indices`)."""
        targets, drivers = link_indices(self.links, skeleton.names)
        return {**self.aligned(styles), "targets": targets, "drivers": drivers}

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        """The forearms of the rows that weigh a coupled style moved with their drivers (`couple`)."""
        return couple(frame.rotations, frame.weights, frame.gait, (rows["targets"], rows["drivers"]), rows), state

    def save(self, path: Path) -> Path:
        links = np.array([f"{t}:{','.join(ds)}" for t, ds in self.links])
        np.savez(path, styles=np.array(self.styles), links=links, mean=self.mean, walk=self.walk, run=self.run)
        return path

    @classmethod
    def load(cls, path: Path) -> Coupling:
        with np.load(path) as z:
            links = tuple((t, tuple(ds.split(","))) for t, ds in (str(s).split(":") for s in z["links"]))
            arrays = (np.asarray(z[k], np.float64) for k in ("mean", "walk", "run"))
            return cls(tuple(str(s) for s in z["styles"]), links, *arrays)

    def with_styles_of(self, other: Coupling) -> Coupling:
        if other.links != self.links:
            raise ValueError("couplings of different links cannot be merged")
        keep = [k for k, s in enumerate(self.styles) if s not in other.styles]
        merged = (np.concatenate([getattr(self, f)[keep], getattr(other, f)]) for f in ("mean", "walk", "run"))
        return Coupling(tuple(self.styles[k] for k in keep) + other.styles, self.links, *merged)

    @classmethod
    def fit(
        cls,
        styles: Sequence[str],
        links: Sequence[Link],
        names: Sequence[str],
        real: Callable[[str, str], list[np.ndarray]],
        made: Callable[[str, str], list[np.ndarray]],
    ) -> Coupling:
        """Per style from `real` and `made` rotations per gait, each link with the ones before applied."""
        targets, drivers = link_indices(links, names)
        means: list[np.ndarray] = []
        gains: dict[str, list[np.ndarray]] = {g: [] for g in GAITS}
        for style in styles:
            ours = {g: np.concatenate(real(style, g)).astype(np.float64) for g in GAITS}
            mean = quat_mean(np.concatenate(list(ours.values())), axis=0)
            means.append(mean)
            for gait in GAITS:
                rows = np.zeros((len(links), drivers.shape[1] * 3 + 1, 3))
                theirs = np.concatenate(made(style, gait)).astype(np.float64)
                for k, (t, ds) in enumerate(zip(targets, drivers)):
                    rows[k] = regression(ours[gait], mean, t, ds) - regression(theirs, mean, t, ds)
                    theirs[:, t] = moved(theirs, mean, t, ds, np.broadcast_to(rows[k], (len(theirs), *rows[k].shape)))
                gains[gait].append(rows)
        return cls(
            tuple(styles),
            tuple((t, tuple(ds)) for t, ds in links),
            np.stack(means),
            *(np.stack(gains[g]) for g in GAITS),
        )


def _coupled(weights: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the rows that weigh a coupled style, every row's weights on coupled styles (B, S))."""
    w = np.asarray(weights, np.float64) * np.asarray(on, np.float64)[None]
    return np.flatnonzero(w.any(axis=1)), w


def couple(
    rotations: np.ndarray,
    weights: np.ndarray,
    share: np.ndarray,
    joints: tuple[np.ndarray, np.ndarray],
    aligned: Mapping[str, np.ndarray],
) -> np.ndarray:
    """Rotations (B, J, 4) coupled toward the styles of weights (B, S), gait-mixed; compiled."""
    from .coupling_kernels import couple_batch

    rows, w = _coupled(weights, aligned["on"])
    if len(rows) == 0:
        return rotations
    share = np.clip(np.asarray(share, np.float64), 0.0, 1.0)
    out = np.array(rotations, np.float64)
    couple_batch(out, rows, w, share, joints, (aligned["mean"], aligned["walk"], aligned["run"]))
    return out.astype(rotations.dtype)
