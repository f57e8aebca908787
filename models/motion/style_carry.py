"""Carry local rotations from one distribution to a style's real one, per joint: Style-ERD's
rotation priors and LPN-FiLM's output prior.

Per style s and joint j, q's deviation d = log(src_s^-1 q) from the source mean (a rotation vector
in the joint's frame, so a twist stays a twist) is mapped by the linear optimal-transport map
between the source's and the style's Gaussians and clamped into the style's real p98 radius:

    f_s(q) = m_s exp(clamp_r_s(M_s d)),   M_s = C^-1/2 (C^1/2 C_s C^1/2)^1/2 C^-1/2

so a typical source frame lands as a typical style frame. A style mix blends the corrections:
q' = q exp(sum_s w_s log(q^-1 f_s(q))); zero weights give q.
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
    """(..., 3, 3) the linear optimal-transport map between zero-mean Gaussians N(0, c_from) ->
    N(0, c_to): symmetric, the smallest displacement that gives the target covariance."""
    r = _sqrtm(c_from)
    r_inv = np.linalg.inv(r)
    return r_inv @ _sqrtm(r @ c_to @ r) @ r_inv


def tangent_stats(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint of rotations (N, J, 4): mean (J, 4), covariance (J, 3, 3) of the deviations from
    it and their CLAMP_PERCENTILE angle (J,), on an even subsample."""
    q = q[np.linspace(0, len(q) - 1, min(len(q), MAX_SAMPLES)).astype(int)]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    mean = quat_mean(q, axis=0)
    d = quat_log(quat_mul(quat_inv(mean)[None], q))
    cov = np.einsum("nji,njk->jik", d, d) / len(d) + 1e-8 * np.eye(3)
    return mean, cov, np.percentile(np.linalg.norm(d, axis=-1), CLAMP_PERCENTILE, axis=0)


@dataclass(frozen=True)
class StyleCarry:
    """Per target style (S) and joint (J): source mean (S, J, 4), style mean (S, J, 4), map
    (S, J, 3, 3), clamp radius (S, J) in radians."""

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
        """From rotations (N, J, 4) to carry and the real ones (N', J, 4), one pair per target
        style; joints in `fixed` are left as they are, joints in `clamp_only` only clamped into
        the style's real range. `source_floor` (radians): the spread the sources are taken to
        have at least along every axis, so an axis they hardly move along (a network that keeps
        a twist still) is not stretched to the style's spread, which would magnify its noise;
        it bounds every gain by the style's spread over the floor."""
        src, tgt = [tangent_stats(q) for q in sources], [tangent_stats(q) for q in targets]
        source = np.stack([s[0] for s in src])
        mean = np.stack([t[0] for t in tgt])
        c_from = np.stack([s[1] for s in src]) + source_floor**2 * np.eye(3)
        lin = gaussian_map(c_from, np.stack([t[1] for t in tgt]))
        return pinned(source, mean, lin, np.stack([t[2] for t in tgt]), fixed, clamp_only)

    @functools.cached_property
    def bounds(self) -> StyleCarry:
        """The clamp alone: each style's rotations kept within its real radius of its mean, not
        carried (`gait.carry_by_gait` holds what another prior carried inside this one's range)."""
        return StyleCarry(
            self.mean, self.mean, np.ascontiguousarray(np.broadcast_to(np.eye(3), self.map.shape)), self.radius
        )

    @functools.cached_property
    def damping(self) -> np.ndarray:
        """(S, J, 3, 3) each map with its gains capped at 1 (the map is symmetric: the capped
        eigen-decomposition): where a style moves a joint less than the carried source it
        shrinks the source's motion, and it never magnifies it (Style-ERD's fast part,
        `models/erd/slow_carry.py`)."""
        vals, vecs = np.linalg.eigh(self.map)
        return (vecs * np.minimum(vals, 1.0)[..., None, :]) @ np.swapaxes(vecs, -1, -2)

    def __call__(self, q: np.ndarray, weights: np.ndarray, hips: int = -1) -> np.ndarray:
        """(B, J, 4) rotations (B, J, 4) carried toward the styles of weights (B, S), compiled
        (`style_carry_kernels.py`; `tests/reference/erd_carry.py` is the reference). Joint `hips` (if >= 0) is carried
        without its heading (its twist about world up), which is put back after."""
        from .style_carry_kernels import carry

        return carry(q, weights, self.source, self.mean, self.map, self.radius, hips)

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(source, mean, map, radius), as the compiled kernels take a carry."""
        return self.source, self.mean, self.map, self.radius

    def with_maps_of(self, other: StyleCarry, styles: Sequence[int], joints: Sequence[int]) -> StyleCarry:
        """This carry with the maps of `styles` x `joints` (index lists) taken from `other`, fitted
        apart on other frames (each joint's map is fitted on its own, so they combine)."""
        arrays = [np.array(a) for a in self.arrays]
        for out, a in zip(arrays, other.arrays):
            out[np.ix_(styles, joints)] = a[np.ix_(styles, joints)]
        return StyleCarry(*(np.ascontiguousarray(a) for a in arrays))

    @classmethod
    def stack(cls, carries: list[StyleCarry]) -> StyleCarry:
        """One carry holding each of `carries`' styles in turn (fitted apart, e.g. each with its
        own fixed joints)."""
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
        """Each row carried by this carry and by `then_b` followed by `then_c`, mixed by the row's
        share (B,): q exp(sum_s w_s [(1 - r) log(q^-1 f_s(q)) + r log(q^-1 c_s(b_s(q)))]), compiled
        (`style_carry_kernels.carry_pair_batch`; the numpy reference is `tests/reference/style_carry.py`). A row at
        share 0 gets exactly what this carry alone gives it."""
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
    """The carry of these arrays (style axis first; changed in place) with the joints `clamp` only
    clamped into each style's range (source mean = style mean, identity map) and the joints
    `fixed` left as they are (identity means and maps, radius pi)."""
    clamp_, fixed_ = list(clamp), list(fixed)
    source[:, clamp_] = mean[:, clamp_]
    lin[:, clamp_] = np.eye(3)
    source[:, fixed_] = mean[:, fixed_] = (0.0, 0.0, 0.0, 1.0)
    lin[:, fixed_] = np.eye(3)
    radius[:, fixed_] = np.pi
    return StyleCarry(source, mean, lin, radius)


def carry_rows(carries: Mapping[str, StyleCarry], joints: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """`stages.style_rows`'s arrays of `carries` (by key prefix): each one's arrays under prefix +
    each of `FIELDS`, beside the row that changes nothing (identity means and maps, infinite radii)."""
    identity = np.tile((0.0, 0.0, 0.0, 1.0), (joints, 1))
    plain = (identity, identity, np.tile(np.eye(3), (joints, 1, 1)), np.full(joints, np.inf))
    return {p + k: (a, row) for p, c in carries.items() for k, a, row in zip(FIELDS, c.arrays, plain)}
