"""Trained LTI style translators and the streaming interface the service calls.

One `StyleTranslator` per output style holds the block-diagonal LTI system (all per-joint
systems combined), the per-DOF normalisation, the training range of the input (for the erf
blend) and the footplant classifier. Every frame, per session:

    u = (features(frame) - in_mean) / in_std          (features: representation.py)
    [x'; y] = M [x; u]     with M = [[A, B], [C, D]]   (one matrix product for the whole batch)
    out = y * out_std + out_mean
    out = (1 - w) out + w in,  w = max_d erf(max(0, dist_d - k_p) / k_c)   (generalisation blend)
    pose = inverse representation(out); contacts from the state; optional foot lock

Heading: the model's own yaw change drifts slowly for some styles (exhausted: ~0.05 deg/frame
on a straight validation walk, a full circle in ~4 minutes of streaming), so by default the output
takes the input's yaw change (`keep_heading=True`); speed, posture and timing stay translated.

The foot lock (on by default) bends the legs by two-bone IK so planted ankles stay where they
touched down; it leaves the root and so the path alone. (A first version shifted the root
instead: the translated legs take shorter strides than the translated root displacement implies,
and the path shrank, 811 -> 459 cm on the elderly validation walk.) The contact flags are always
returned in `FrameBatch.contacts`.

The log-time-warp output (last output DOF) is only used offline (`translate_motion(...,
timewarp=True)`); online it is ignored, since honouring it would break synchrony.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.special import erf

from models.motion.assets import bandai_namco_skeleton
from models.motion.rotations import quat_mul

from . import representation as rep
from .footplant import FootLock, FootplantClassifier

SHARED_KEYS = ("started", "in_yaw", "in_ground", "out_yaw", "out_ground", "lock_anchor", "lock_since", "lock_was")
SPARSE_BATCH = 16  # from this batch size on the sparse product is faster than the dense one
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights" / "lti"


@dataclass
class StyleTranslator:
    style: str
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    in_mean: np.ndarray
    in_std: np.ndarray
    out_mean: np.ndarray
    out_std: np.ndarray
    in_lo: np.ndarray  # per-DOF training range of the normalised input
    in_hi: np.ndarray
    orders: np.ndarray  # state dimension of each per-joint block (root first)
    k_p: float = 1.0
    k_c: float = 2.0
    footplant: FootplantClassifier | None = None
    meta: dict = field(default_factory=dict)
    ref: np.ndarray = field(default_factory=lambda: rep.IDENTITY_REF.copy())  # (22, 4) per-joint reference rotations
    keep_heading: bool = True  # output yaw change := input yaw change (no heading drift); not stored

    def __post_init__(self) -> None:
        n = self.A.shape[0]
        self.M = np.block([[self.A, self.B], [self.C, self.D]])
        self.MT = np.ascontiguousarray(self.M.T)
        self.MS = sparse.csr_matrix(self.M)  # block-diagonal structure: ~95% zeros, used for large batches
        self.n = n

    @property
    def state_dim(self) -> int:
        return self.n

    # ---------------------------------------------------------------- core

    def blend_weight(self, u: np.ndarray) -> np.ndarray:
        """(..., 67) normalised input -> (...,) erf blend weight: 0 within the training range
        (plus k_p standard deviations), -> 1 far outside."""
        dist = np.maximum(np.maximum(u - self.in_hi, self.in_lo - u), 0.0)
        return erf(np.maximum(dist - self.k_p, 0.0) / self.k_c).max(axis=-1)

    def _finish(self, feats: np.ndarray, u: np.ndarray, y: np.ndarray, blend: bool) -> np.ndarray:
        out = y * self.out_std + self.out_mean
        if blend:
            w = self.blend_weight(u)[..., None]
            out = out.copy()
            out[..., :rep.FEATURE_DIM] = (1 - w) * out[..., :rep.FEATURE_DIM] + w * feats
            out[..., rep.FEATURE_DIM:] *= 1 - w
        if self.keep_heading:
            out = out.copy() if not blend else out
            out[..., 2] = feats[..., 2]
        return out

    def translate_features(self, feats: np.ndarray, blend: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Offline: (F, 67) input features -> ((F, 68) output features, (F, n) states after each frame)."""
        u = (feats - self.in_mean) / self.in_std
        x = np.zeros(self.n)
        ys = np.empty((len(u), self.M.shape[0] - self.n))
        xs = np.empty((len(u), self.n))
        for t in range(len(u)):
            z = self.M @ np.concatenate([x, u[t]])
            x, ys[t] = z[: self.n], z[self.n:]
            xs[t] = x
        return self._finish(feats, u, ys, blend), xs

    def translate_motion(self, motion, timewarp: bool = False, blend: bool = True, footlock: bool = True):
        """Offline translation of a whole `Motion` (BN skeleton). Returns (Motion, contacts (F', 2))."""
        from dataclasses import replace
        feats = rep.motion_to_features(motion, self.ref)
        out, xs = self.translate_features(feats, blend)
        yaw0, _ = rep.split_hips(motion.rotations[0, rep.HIPS])
        root, rots = rep.features_to_sequence(out[:, : rep.FEATURE_DIM], motion.translations[0, rep.HIPS, [0, 2]], float(yaw0), self.ref)
        contacts = self.footplant.predict(xs) if self.footplant is not None else np.zeros((len(out), 2), bool)
        if footlock and self.footplant is not None:
            lock = FootLock(motion.skeleton, 1)
            for t in range(len(root)):
                rots[t:t + 1] = lock(root[t:t + 1], rots[t:t + 1], contacts[t:t + 1])
        if timewarp:
            from .warping import resample_pose
            rate = np.exp(out[:, rep.FEATURE_DIM])  # output frames per input frame
            clock = np.concatenate([[0.0], np.cumsum(rate[1:])])  # output time of each input frame
            times = np.interp(np.arange(0.0, clock[-1] + 1e-9), clock, np.arange(len(clock)))
            root, rots = resample_pose(root, rots, times)
            contacts = contacts[np.clip(np.round(times).astype(int), 0, len(contacts) - 1)]
        translations = np.broadcast_to(motion.translations[:1], (len(root),) + motion.translations.shape[1:]).copy()
        translations[:, rep.HIPS] = root
        return replace(motion, rotations=rots, translations=translations), contacts

    # ---------------------------------------------------------------- persistence

    def save(self, path: Path) -> None:
        extra = self.footplant.to_arrays() if self.footplant is not None else {}
        np.savez_compressed(
            path, style=np.array(self.style), A=self.A.astype(np.float32), B=self.B.astype(np.float32),
            C=self.C.astype(np.float32), D=self.D.astype(np.float32), in_mean=self.in_mean, in_std=self.in_std,
            out_mean=self.out_mean, out_std=self.out_std, in_lo=self.in_lo, in_hi=self.in_hi, orders=self.orders,
            k=np.array([self.k_p, self.k_c]), ref=self.ref, meta=np.array(repr(self.meta)), **extra)

    @classmethod
    def load(cls, path: Path) -> StyleTranslator:
        with np.load(path) as z:
            fp = FootplantClassifier.from_arrays(z) if "fp_w" in z else None
            return cls(str(z["style"]), *(z[k].astype(np.float64) for k in ("A", "B", "C", "D")),
                       z["in_mean"], z["in_std"], z["out_mean"], z["out_std"], z["in_lo"], z["in_hi"], z["orders"],
                       float(z["k"][0]), float(z["k"][1]), fp, {"source": str(path)}, z["ref"])


def _mix_rotations(parts: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Weighted quaternion blend of parts [(w (B,), q (B, J, 4))]: signs aligned to each row's
    heaviest part, then normalised; a row with one part of weight 1 gets that part unchanged."""
    weights = np.stack([w for w, _ in parts])  # (K, B)
    quats = np.stack([q for _, q in parts])  # (K, B, J, 4)
    rows = np.arange(weights.shape[1])
    base = quats[weights.argmax(axis=0), rows]
    sign = np.where((quats * base).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    acc = (weights[..., None, None] * sign * quats).sum(axis=0)
    return acc / np.linalg.norm(acc, axis=-1, keepdims=True)


class LTIStyleModel:
    """Hsu et al. 2005 LTI style translation behind the project's streaming interface
    (`models/interface.py`); the input style is Bandai Namco `normal`.

    State per session (all arrays, session axis first): the LTI state of each style in its own
    array `x.<style>` (a style whose weight is 0 is held at x = 0, its identified initial state),
    the previous input root transform, the integrated output root transform and the foot-lock
    memory.
    A style weight vector w mixes the styles: the root displacement features are blended
    linearly, joint rotations by normalised quaternion blending, and 1 - sum(w) of the input
    passes through (intensity < 1). With a one-hot w this is exactly the paper's translator.

    The style set can change while sessions run: `add_style(translator)` appends a style to
    `styles()`, `remove_style(name)` drops one, and `upgrade_state` brings a state made before
    (a live session's, a snapshot's) to the current set: a new style's `x.<style>` starts at 0, a
    removed style's is dropped, nothing else changes. Both replace (never mutate) `translators`
    and the style list, so readers on other threads see a consistent set and `copy.copy(model)`
    is a model whose style set changes independently of this one.
    """

    name = "lti"
    fps = 30.0  # the Bandai Namco rate it was identified at

    def __init__(self, translators: dict[str, StyleTranslator] | None = None, weights_dir: Path | str = WEIGHTS_DIR,
                 blend: bool = True, footlock: bool = True, keep_heading: bool = True, skeleton=None):
        if translators is None:
            translators = {}
            for path in sorted(Path(weights_dir).glob("*.npz")):
                t = StyleTranslator.load(path)
                translators[t.style] = t
        if not translators:
            raise FileNotFoundError(f"no LTI weights (*.npz) in {weights_dir}")
        self.translators = dict(translators)
        for tr in translators.values():
            tr.keep_heading = keep_heading
        self.keep_heading = keep_heading
        self.blend = blend
        self.footlock = footlock
        self.skeleton = skeleton if skeleton is not None else bandai_namco_skeleton()
        self._set_styles(sorted(translators))

    def styles(self) -> list[str]:
        return list(self._styles)

    @property
    def state_dim(self) -> int:
        """Total LTI state size over all styles."""
        return sum(self.translators[s].n for s in self._styles)

    # ---------------------------------------------------------------- style set

    def _set_styles(self, styles: list[str]) -> None:
        self._styles = styles
        self._state_keys = frozenset(SHARED_KEYS) | {f"x.{s}" for s in styles}

    def add_style(self, tr: StyleTranslator) -> None:
        """Append the style of `tr` (a new name) to `styles()`; running sessions are unaffected."""
        if tr.style in self.translators:
            raise ValueError(f"style {tr.style!r} already exists")
        tr.keep_heading = self.keep_heading
        self.translators = {**self.translators, tr.style: tr}
        self._set_styles(self._styles + [tr.style])

    def remove_style(self, style: str) -> None:
        """Drop `style`; sessions that used it carry on with its share passing the input through."""
        if style not in self.translators:
            raise KeyError(f"no style {style!r}")
        if len(self._styles) == 1:
            raise ValueError("cannot remove the model's last style")
        self._set_styles([s for s in self._styles if s != style])
        self.translators = {k: v for k, v in self.translators.items() if k != style}

    def upgrade_state(self, state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`state` on the current style set: added styles at x = 0, removed ones dropped (see
        `models.interface`); `state` itself when it already is (one key-set comparison)."""
        if state.keys() == self._state_keys and all(state[f"x.{s}"].shape[1] == self.translators[s].n for s in self._styles):
            return state
        batch = len(state["started"])
        out = {k: state[k] for k in SHARED_KEYS}
        for s in self._styles:
            x, n = state.get(f"x.{s}"), self.translators[s].n
            out[f"x.{s}"] = x if x is not None and x.shape[1] == n else np.zeros((batch, n))
        return out

    def init_state(self, batch: int) -> dict[str, np.ndarray]:
        return {
            **{f"x.{s}": np.zeros((batch, self.translators[s].n)) for s in self._styles},
            "started": np.zeros(batch, bool),
            "in_yaw": np.zeros(batch), "in_ground": np.zeros((batch, 2)),
            "out_yaw": np.zeros(batch), "out_ground": np.zeros((batch, 2)),
            "lock_anchor": np.zeros((batch, 2, 3)), "lock_since": np.full((batch, 2), 10**6),
            "lock_was": np.zeros((batch, 2), bool),
        }

    def step_batch(self, state: dict[str, np.ndarray], frames, style_weights: np.ndarray):
        from models.interface import FrameBatch

        root, rotations = frames.root, frames.rotations
        w = np.asarray(style_weights, dtype=np.float64)
        batch = len(root)
        fresh = ~state["started"]
        yaw, tilt = rep.split_hips(rotations[:, rep.HIPS])
        ground = root[:, [0, 2]]
        prev_yaw = np.where(fresh, yaw, state["in_yaw"])
        prev_ground = np.where(fresh[:, None], ground, state["in_ground"])
        delta = np.empty((batch, 3))
        delta[:, :2] = rep.rotate_y(ground - prev_ground, -prev_yaw)
        delta[:, 2] = rep.wrap(yaw - prev_yaw)

        new_state = {}
        rest = np.clip(1.0 - w.sum(axis=1), 0.0, None)  # share of the input passing through
        body_in = rotations.copy()
        body_in[:, rep.HIPS] = tilt
        root_feats = rest[:, None] * np.concatenate([delta, root[:, 1:2]], axis=1)
        parts = [(rest, body_in)]
        votes = np.zeros((batch, 2))
        for s, style in enumerate(self._styles):
            x = new_state[f"x.{style}"] = state[f"x.{style}"].copy()
            rows = np.nonzero(w[:, s] > 0)[0]
            x[np.nonzero(w[:, s] <= 0)[0]] = 0.0  # inactive styles rest at their initial state
            if len(rows) == 0:
                continue
            tr = self.translators[style]
            _, _, static = rep.pose_features(root[rows], rotations[rows], tr.ref)
            feats = np.concatenate([delta[rows], static], axis=1)
            u = (feats - tr.in_mean) / tr.in_std
            zin = np.concatenate([x[rows], u], axis=1)
            z = (tr.MS @ zin.T).T if len(rows) >= SPARSE_BATCH else zin @ tr.MT
            x[rows] = z[:, : tr.n]
            out = tr._finish(feats, u, z[:, tr.n:], self.blend)
            ws = w[rows, s]
            root_feats[rows] += ws[:, None] * out[:, :4]
            q = np.zeros_like(body_in)
            q[rows] = rep.static_to_rotations(out[:, 4: rep.FEATURE_DIM], np.zeros(len(rows)), tr.ref)
            weights = np.zeros(batch)
            weights[rows] = ws
            parts.append((weights, np.where(weights[:, None, None] > 0, q, body_in)))
            if tr.footplant is not None:
                votes[rows] += ws[:, None] * tr.footplant.predict(x[rows])

        # integrate the output path: the first frame starts where the input is
        out_yaw = np.where(fresh, yaw, state["out_yaw"] + root_feats[:, 2])
        out_ground = np.where(fresh[:, None], ground, state["out_ground"] + rep.rotate_y(root_feats[:, :2], state["out_yaw"]))
        body = _mix_rotations(parts)
        out_rot = body.copy()
        out_rot[:, 0] = (0.0, 0.0, 0.0, 1.0)
        out_rot[:, rep.HIPS] = quat_mul(rep.qyaw(out_yaw), body[:, rep.HIPS])
        out_root = np.stack([out_ground[:, 0], root_feats[:, 3], out_ground[:, 1]], axis=-1)
        total = w.sum(axis=1)
        contacts = (votes > 0.5 * np.maximum(total, 1e-12)[:, None]) & (total[:, None] > 0)

        new_state.update({"started": np.ones(batch, bool), "in_yaw": yaw, "in_ground": ground,
                          "out_yaw": out_yaw, "out_ground": out_ground,
                          "lock_anchor": state["lock_anchor"], "lock_since": state["lock_since"], "lock_was": state["lock_was"]})
        if self.footlock:
            lock = FootLock(self.skeleton, batch)
            lock.anchor, lock.since, lock.was = state["lock_anchor"].copy(), state["lock_since"].copy(), state["lock_was"].copy()
            out_rot = lock(out_root, out_rot, contacts)
            new_state.update(lock_anchor=lock.anchor, lock_since=lock.since, lock_was=lock.was)
        return FrameBatch(out_root, out_rot, contacts), new_state
