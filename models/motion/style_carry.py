"""Carry local rotations from one distribution to a style's real one, per joint: Style-ERD's
rotation priors and LPN-FiLM's output prior.

q's deviation d = log(src_s^-1 q) (joint frame, so a twist stays a twist) is mapped by the linear
optimal-transport map between source and style Gaussians and clamped into the real p98 radius:

    f_s(q) = m_s exp(clamp_r_s(M_s d)),   M_s = C^-1/2 (C^1/2 C_s C^1/2)^1/2 C^-1/2

A style mix blends the corrections: q' = q exp(sum_s w_s log(q^-1 f_s(q))).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .rotations import quat_inv, quat_log, quat_mean, quat_mul

CLAMP_PERCENTILE = 98.0
FIELDS = ("source", "mean", "map", "radius")  # a carry's arrays, as files and stages' rows name them
MAX_SAMPLES = 60_000  # an even subsample per style keeps a fit to seconds


def _sqrtm(c: np.ndarray) -> np.ndarray:
    """Square root of symmetric positive semi-definite matrices (..., 3, 3)."""
    w, v = np.linalg.eigh(c)
    return (v * np.sqrt(np.maximum(w, 0.0))[..., None, :]) @ np.swapaxes(v, -1, -2)


def gaussian_map(c_from: np.ndarray, c_to: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the linear optimal-transport map N(0, c_from) -> N(0, c_to)."""
    r = _sqrtm(c_from)
    r_inv = np.linalg.inv(r)
    return r_inv @ _sqrtm(r @ c_to @ r) @ r_inv


def tangent_stats(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint: mean (J, 4), deviation covariance (J, 3, 3), CLAMP_PERCENTILE angle (J,)."""
    q = q[np.linspace(0, len(q) - 1, min(len(q), MAX_SAMPLES)).astype(int)]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    mean = quat_mean(q, axis=0)
    d = quat_log(quat_mul(quat_inv(mean)[None], q))
    cov = np.einsum("nji,njk->jik", d, d) / len(d) + 1e-8 * np.eye(3)
    return mean, cov, np.percentile(np.linalg.norm(d, axis=-1), CLAMP_PERCENTILE, axis=0)


@dataclass(frozen=True)
class StyleCarry:
    """Per style and joint: source mean, style mean, map (S, J, 3, 3), clamp radius (radians)."""

    source: np.ndarray
    mean: np.ndarray
    map: np.ndarray
    radius: np.ndarray

    @classmethod
    def fit(
        cls,
        sources: list[np.ndarray],
        targets: list[np.ndarray],
        fixed: tuple[int, ...] = (),
        clamp_only: tuple[int, ...] = (),
        source_floor: float = 0.0,
    ) -> StyleCarry:
        """From rotations (N, J, 4) to the real ones, one pair per style; `fixed` joints left alone,
        `clamp_only` ones only clamped. `source_floor` (radians): the least spread the sources are
        taken to have, so an axis they hardly move along is not stretched (magnifying its noise)."""
        src, tgt = [tangent_stats(q) for q in sources], [tangent_stats(q) for q in targets]
        source = np.stack([s[0] for s in src])
        mean = np.stack([t[0] for t in tgt])
        c_from = np.stack([s[1] for s in src]) + source_floor**2 * np.eye(3)
        lin = gaussian_map(c_from, np.stack([t[1] for t in tgt]))
        return pinned(source, mean, lin, np.stack([t[2] for t in tgt]), fixed, clamp_only)

    @functools.cached_property
    def bounds(self) -> StyleCarry:
        """The clamp alone: rotations kept within each style's real radius, not carried."""
        return StyleCarry(
            self.mean, self.mean, np.ascontiguousarray(np.broadcast_to(np.eye(3), self.map.shape)), self.radius
        )

    @functools.cached_property
    def damping(self) -> np.ndarray:
        """(S, J, 3, 3) each map with gains capped at 1: it never magnifies the source's motion."""
        vals, vecs = np.linalg.eigh(self.map)
        return (vecs * np.minimum(vals, 1.0)[..., None, :]) @ np.swapaxes(vecs, -1, -2)

    def __call__(self, q: np.ndarray, weights: np.ndarray, hips: int = -1) -> np.ndarray:
        """Rotations (B, J, 4) carried toward the styles of weights (B, S), compiled."""
        from .style_carry_kernels import carry

        return carry(q, weights, self.source, self.mean, self.map, self.radius, hips)

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(source, mean, map, radius), as the compiled kernels take a carry."""
        return self.source, self.mean, self.map, self.radius

    def with_maps_of(self, other: StyleCarry, styles: Sequence[int], joints: Sequence[int]) -> StyleCarry:
        """This carry with the maps of `styles` x `joints` from `other` (maps are per joint)."""
        arrays = [np.array(a) for a in self.arrays]
        for out, a in zip(arrays, other.arrays):
            out[np.ix_(styles, joints)] = a[np.ix_(styles, joints)]
        return StyleCarry(*(np.ascontiguousarray(a) for a in arrays))

    @classmethod
    def stack(cls, carries: list[StyleCarry]) -> StyleCarry:
        """One carry holding each of `carries`' styles in turn."""
        return cls(*(np.concatenate([getattr(c, f) for c in carries]) for f in FIELDS))

    def mixed_with(
        self,
        then_b: StyleCarry,
        then_c: StyleCarry,
        q: np.ndarray,
        weights: np.ndarray,
        share: np.ndarray,
        hips: int = -1,
    ) -> np.ndarray:
        """Rows carried by this and by `then_b` then `then_c`, mixed by share (`carry_pair_batch`)."""
        from .style_carry_kernels import carry_pair

        return carry_pair(q, weights, share, self.arrays, then_b.arrays, then_c.arrays, hips)

    def named(self, prefix: str = "") -> dict[str, np.ndarray]:
        """Its arrays under `prefix` + each of `FIELDS`, as a file holds them (`read` reads them back)."""
        return {prefix + k: a for k, a in zip(FIELDS, self.arrays)}

    @classmethod
    def read(cls, arrays: Mapping[str, np.ndarray], prefix: str = "") -> StyleCarry:
        """The carry `named(prefix)` wrote into `arrays` (an open .npz or its dict)."""
        return cls(*(np.ascontiguousarray(arrays[prefix + k], np.float64) for k in FIELDS))

    def save(self, path: Path) -> Path:
        np.savez(path, source=self.source, mean=self.mean, map=self.map, radius=self.radius)
        return path

    @classmethod
    def load(cls, path: Path) -> StyleCarry:
        with np.load(path) as z:
            return cls.read(z)


def pinned(
    source: np.ndarray,
    mean: np.ndarray,
    lin: np.ndarray,
    radius: np.ndarray,
    fixed: Sequence[int],
    clamp: Sequence[int],
) -> StyleCarry:
    """These arrays' carry (changed in place) with `clamp` joints only clamped and `fixed` ones left."""
    clamp_, fixed_ = list(clamp), list(fixed)
    source[:, clamp_] = mean[:, clamp_]
    lin[:, clamp_] = np.eye(3)
    source[:, fixed_] = mean[:, fixed_] = (0.0, 0.0, 0.0, 1.0)
    lin[:, fixed_] = np.eye(3)
    radius[:, fixed_] = np.pi
    return StyleCarry(source, mean, lin, radius)


def carry_rows(carries: Mapping[str, StyleCarry], joints: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """`stages.style_rows`'s arrays of `carries`, beside the row that changes nothing."""
    identity = np.tile((0.0, 0.0, 0.0, 1.0), (joints, 1))
    plain = (identity, identity, np.tile(np.eye(3), (joints, 1, 1)), np.full(joints, np.inf))
    return {p + k: (a, row) for p, c in carries.items() for k, a, row in zip(FIELDS, c.arrays, plain)}
