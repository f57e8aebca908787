"""Training: pairs -> correspondence (IMW) -> representation -> per-joint subspace identification
-> block-diagonal translator -> footplant classifier -> evaluation on held-out validation pairs.

`python -m models.lti train [--styles elderly exhausted]`; everything else is in CONFIG below.
Deterministic: pairing and alignment have no randomness, and numpy is seeded.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..motion.rotation_ball import fit_prior
from ..motion.rotations import quat_angle, quat_exp
from . import representation as rep
from .footplant import FootplantClassifier, contact_labels
from .model import WEIGHTS_DIR, StyleTranslator
from .subspace import StateSpace, spectral_radius, subspace_id
from .warping import imw, resample_pose

_UPPER = (2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13)  # Spine .. Hand_R
_LEGS = (14, 15, 16, 17, 18, 19, 20, 21)  # UpperLeg_L .. Toes_R
CONTEXT = {
    **{j: [1, 14, 18] + [k for k in _UPPER if k != j] for j in _UPPER},  # Hips (root), UpperLegs, upper body
    **{j: [1, 7, 11] + [k for k in _LEGS if k != j] for j in _LEGS},  # Hips (root), UpperArms, legs
}

CONFIG: dict[str, Any] = dict(
    datasets=["bandai-namco-2", "bandai-namco-1"],
    input_style="normal",
    # None: every dataset-2 style but the input's (`bn1-<style>` trains dataset 1's: MODEL_CARD.md)
    styles=None,
    contents=None,  # None: every content; or e.g. ["walk", "walk-turn-left", "walk-turn-right"]
    align="imw",  # the alignment (`warping.imw`), recorded in the report and the alignment cache key
    # max_step 9: slopes up to 3 output frames per input frame, for the slowest styles (~2.5x)
    imw=dict(s=3, max_step=9, lam=1000.0, mu=1.0, max_iter=8, tol=1e-4),
    match_std_floor=0.05,  # rad / cm, for the matching features only
    norm_std_floor=1e-2,
    horizon=10,  # block rows of the subspace method
    energy=0.99,  # singular-value energy kept when no clear gap
    max_order_root=16,
    # True: the root's travel a system of its own; False: the paper's one (docs/eval/ablation.md)
    split_root=False,
    max_order_joint=8,
    # spectral radius cap for A: slower modes hold a gesture for seconds (MODEL_CARD.md)
    max_radius=0.9,
    # {joint: [other joints]} whose rotations a joint's system also reads; empty: the paper's one
    # joint per system. Without it a raise-up's spine cannot differ from a wave's, nor the arms
    # swing with the stride (MODEL_CARD.md).
    context=CONTEXT,
    # ... fitted as if those inputs carried noise of this std (normalised; subspace.fit_bd): a plain
    # fit of many correlated inputs takes large cancelling gains that amplify a stream's noise
    context_noise=0.3,
    # ... and every rotation input as if it carried this noise (radians): a DOF that barely moves
    # in training (a knee's twist) otherwise takes large gains, and a stream's noise jerks the leg
    rotation_noise=1e-2,
    # rotation prior (`style_prior`): radii from the output style's TRAIN clips
    prior_inner_q=97.0,
    prior_outer_q=99.0,
    prior_margin_deg=1.0,
    k_p=1.0,  # erf blend: tolerance (std) outside the training range before blending starts
    k_c=2.0,  # erf blend: softness (std)
    seed=0,
)

ROTATION_DOFS = rep.ROOT_DIMS - 3  # features from here on are rotations (the hips' tilt, then the joints)
GROUND_DOFS = np.arange(3)  # the root's ground displacement (x, z) and yaw change


def joint_dofs(j: int) -> np.ndarray:
    """Feature indices of joint j: a body joint's three, the Hips' root 7, `joint_Root`'s travel."""
    if j == 0:
        return GROUND_DOFS
    if j == rep.HIPS:
        return np.arange(rep.ROOT_DIMS)
    k = j - rep.BODY_JOINTS[0]
    return np.arange(rep.ROOT_DIMS + 3 * k, rep.ROOT_DIMS + 3 * k + 3)


def groups(cfg=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(input DOFs, output DOFs) of each per-joint system, the root's first (it drives the time warp)."""
    cfg = cfg or CONFIG
    context = {int(k): v for k, v in (cfg.get("context") or {}).items()}  # JSON keys are strings
    root = np.arange(rep.ROOT_DIMS)
    if cfg.get("split_root", False):
        out = [(GROUND_DOFS, np.r_[GROUND_DOFS, rep.FEATURE_DIM]), (root, root[len(GROUND_DOFS) :])]
    else:
        out = [(root, np.r_[root, rep.FEATURE_DIM])]
    for j in rep.BODY_JOINTS:
        own = joint_dofs(j)
        extra = [joint_dofs(c) for c in context.get(j, ()) if c != j]
        out.append((np.concatenate([own, *extra]) if extra else own, own))
    return out


# --------------------------------------------------------------------------- pairs


def dataset_of(model_style: str) -> tuple[str, str]:
    """Model name -> (dataset, style label): "elderly" is dataset 2, "bn1-old" is dataset 1's "old"."""
    if model_style.startswith("bn1-"):
        return "bandai-namco-1", model_style[4:]
    return "bandai-namco-2", model_style


def warpable(cfg=CONFIG) -> tuple[float, float]:
    """The range of length ratios (output / input) the IMW warp can represent, with a margin."""
    s, ms = cfg["imw"]["s"], cfg["imw"]["max_step"]
    return 1.0 / s * 1.15, ms / s / 1.15


def make_pairs(index, style: str, split: str, cfg=CONFIG) -> list[tuple]:
    """Each output clip paired with the same-content input clip closest in length within the warp's
    limits (dataset 1, one take per pair: from any split)."""
    from models.data import select

    dataset, label = dataset_of(style)
    lo, hi = warpable(cfg)
    pairs: list[tuple] = []
    used: dict[str, int] = {}
    in_split = split if dataset == "bandai-namco-2" else ("train", "val", "test")
    for out_clip in select(index, dataset=dataset, style=label, split=split):
        if cfg["contents"] and out_clip.content not in cfg["contents"]:
            continue
        cands = [
            c
            for c in select(index, dataset=dataset, style=cfg["input_style"], content=out_clip.content, split=in_split)
            if lo <= out_clip.frames / c.frames <= hi
        ]
        if not cands:
            continue
        best = min(
            cands, key=lambda c: (round(abs(math.log(out_clip.frames / c.frames)), 1), used.get(c.key, 0), c.name)
        )
        used[best.key] = used.get(best.key, 0) + 1
        pairs.append((best, out_clip))
    return pairs


@dataclass
class PairData:
    u: np.ndarray  # (T, 67) input features
    y: np.ndarray  # (T, 68) output features (time-warped) + log time warp
    contacts: np.ndarray  # (T, 2) output contacts
    warp: np.ndarray


def _cache_dir() -> Path:
    from models.settings import get_settings

    d = Path(get_settings().cache_dir) / "lti" / "align"
    d.mkdir(parents=True, exist_ok=True)
    return d


def reference_rotations(index, cfg=CONFIG) -> np.ndarray:
    from models.data import load_motion, select

    clips = select(index, dataset="bandai-namco-2", style=cfg["input_style"], split="train")
    return rep.mean_rotations(np.concatenate([load_motion(c).rotations for c in clips]))


def match_features(feats: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    return (feats[:, 3:] - mean[3:]) / std[3:]


def align(in_motion, out_motion, match_mean, match_std, ref, cfg=CONFIG):
    x = match_features(rep.motion_to_features(in_motion, ref), match_mean, match_std)
    y = match_features(rep.motion_to_features(out_motion, ref), match_mean, match_std)
    return imw(x, y, **cfg["imw"]).warp


def pair_from_warp(mi, mo, warp: np.ndarray, ref) -> PairData:
    """A training pair: output features resampled along the warp, the log differential warp, contacts."""
    from models.motion.skeleton import fk

    root, rots = resample_pose(mo.translations[:, rep.HIPS], mo.rotations, warp)
    fo = rep.sequence_features(root, rots, ref)
    d = np.diff(warp)
    rate = np.concatenate([d[:1], d]) if len(d) else np.ones(1)
    y = np.concatenate([fo, np.log(np.maximum(rate, 1e-3))[:, None]], axis=1)
    trans = np.broadcast_to(mo.translations[:1], (len(root),) + mo.translations.shape[1:]).copy()
    trans[:, rep.HIPS] = root
    _, pos = fk(rots, trans, mo.skeleton.parents)
    return PairData(rep.motion_to_features(mi, ref), y, contact_labels(pos, mo.skeleton, mo.fps), warp)


def pair_data(in_clip, out_clip, match_mean, match_std, ref, cfg=CONFIG) -> PairData:
    """`pair_from_warp` for two dataset clips, the IMW alignment cached on disk."""
    from models.data import load_motion

    key = hashlib.sha1(
        json.dumps([in_clip.key, out_clip.key, cfg["align"], cfg["imw"], cfg["match_std_floor"], "ref-v1"]).encode()
    ).hexdigest()[:16]
    cache = _cache_dir() / f"{key}.npy"
    mi, mo = load_motion(in_clip), load_motion(out_clip)
    if cache.exists():
        warp = np.load(cache)
    else:
        warp = align(mi, mo, match_mean, match_std, ref, cfg)
        np.save(cache, warp)
    return pair_from_warp(mi, mo, warp, ref)


def matching_stats(index, ref, cfg=CONFIG) -> tuple[np.ndarray, np.ndarray]:
    from models.data import load_motion, select

    clips = select(index, dataset="bandai-namco-2", style=cfg["input_style"], split="train")
    feats = np.concatenate([rep.motion_to_features(load_motion(c), ref) for c in clips])
    return feats.mean(0), np.maximum(feats.std(0), cfg["match_std_floor"])


# --------------------------------------------------------------------------- identification


def input_noise(ii: np.ndarray, oo: np.ndarray, in_std: np.ndarray, cfg=CONFIG) -> np.ndarray:
    """Normalised noise std each input of a system is fitted as carrying (`subspace.fit_bd`): a DOF
    with almost no training spread is as loud as any other once normalised."""
    context = np.where(np.isin(ii, oo), 0.0, cfg.get("context_noise", 0.0))
    rotation = np.where(ii >= ROTATION_DOFS, cfg.get("rotation_noise", 0.0) / in_std[ii], 0.0)
    return np.sqrt(context**2 + rotation**2)


def identify(
    data: list[PairData], style: str, ref: np.ndarray, cfg=CONFIG, progress=None
) -> tuple[StyleTranslator, list[StateSpace]]:
    U = np.concatenate([d.u for d in data])
    Y = np.concatenate([d.y for d in data])
    in_mean, in_std = U.mean(0), np.maximum(U.std(0), cfg["norm_std_floor"])
    out_mean, out_std = Y.mean(0), np.maximum(Y.std(0), cfg["norm_std_floor"])
    recs = [((d.u - in_mean) / in_std, (d.y - out_mean) / out_std) for d in data]
    systems = []
    for g, (ii, oo) in enumerate(groups(cfg)):
        sub = [(u[:, ii], y[:, oo]) for u, y in recs]
        max_order = cfg["max_order_root"] if g == 0 else cfg["max_order_joint"]
        noise = input_noise(ii, oo, in_std, cfg)
        systems.append(
            subspace_id(
                sub,
                horizon=cfg["horizon"],
                max_order=max_order,
                energy=cfg["energy"],
                max_radius=cfg["max_radius"],
                input_noise=noise,
            )
        )
        if progress is not None:
            progress.set_postfix_str(f"{style} system {g} n={systems[-1].order}")
            progress.update(1)
    n = sum(s.order for s in systems)
    A, B = np.zeros((n, n)), np.zeros((n, rep.FEATURE_DIM))
    C, D = np.zeros((rep.FEATURE_DIM + 1, n)), np.zeros((rep.FEATURE_DIM + 1, rep.FEATURE_DIM))
    k = 0
    for (ii, oo), s in zip(groups(cfg), systems):
        sl = slice(k, k + s.order)
        A[sl, sl] = s.A
        B[sl, ii] = s.B
        C[np.ix_(oo, np.arange(k, k + s.order))] = s.C
        D[np.ix_(oo, ii)] = s.D
        k += s.order
    U_n = np.concatenate([u for u, _ in recs])
    # the stored matrices are float32: identify the footplant classifier on what will be used
    A, B, C, D = (m.astype(np.float32).astype(np.float64) for m in (A, B, C, D))
    orders = np.array([s.order for s in systems])
    tr = StyleTranslator(
        style, A, B, C, D, in_mean, in_std, out_mean, out_std, U_n.min(0), U_n.max(0), orders, cfg["k_p"], cfg["k_c"],
        ref=ref,
    )  # fmt: skip
    states = np.concatenate([tr.translate_features(d.u, blend=False)[1] for d in data])
    tr.footplant = FootplantClassifier.fit(states, np.concatenate([d.contacts for d in data]))
    return tr, systems


def style_prior(index, style: str, cfg=CONFIG) -> tuple[np.ndarray, np.ndarray]:
    """The style's rotation prior from all its TRAIN clips: a linear map carries a raised arm or a bent
    knee past anything the style shows."""
    from models.data import load_motions, select

    dataset, label = dataset_of(style)
    rotations = np.concatenate(
        [m.rotations for m in load_motions(select(index, dataset=dataset, style=label, split="train"))]
    )
    return fit_prior(rotations, cfg["prior_inner_q"], cfg["prior_outer_q"], cfg["prior_margin_deg"])


# --------------------------------------------------------------------------- evaluation


def _angle_error_deg(fa: np.ndarray, fb: np.ndarray) -> float:
    """Mean geodesic angle between the body-joint rotations of two feature arrays."""
    qa = quat_exp(fa[:, 7:67].reshape(-1, 20, 3))
    qb = quat_exp(fb[:, 7:67].reshape(-1, 20, 3))
    return float(np.degrees(quat_angle(qa, qb)).mean())


def evaluate(tr: StyleTranslator, data: list[PairData]) -> dict[str, float]:
    """Held-out reconstruction error (no blend) vs the identity baseline (output = input)."""
    err_n, base_n, ang, base_ang, speed, base_speed, contact_acc = [], [], [], [], [], [], []
    for d in data:
        out, xs = tr.translate_features(d.u, blend=False)
        err_n.append(np.mean(((out - d.y) / tr.out_std) ** 2))
        base = np.concatenate([d.u, np.zeros((len(d.u), 1))], axis=1)
        base_n.append(np.mean(((base - d.y) / tr.out_std) ** 2))
        ang.append(_angle_error_deg(out, d.y))
        base_ang.append(_angle_error_deg(d.u, d.y))
        sp = lambda f: np.linalg.norm(f[:, :2], axis=1) * 30.0
        speed.append(np.mean(np.abs(sp(out) - sp(d.y))))
        base_speed.append(np.mean(np.abs(sp(d.u) - sp(d.y))))
        if tr.footplant is not None:
            contact_acc.append(np.mean(tr.footplant.predict(xs) == d.contacts))
    return {
        "pairs": len(data),
        "rmse_norm": float(np.sqrt(np.mean(err_n))),
        "rmse_norm_identity": float(np.sqrt(np.mean(base_n))),
        "joint_angle_deg": float(np.mean(ang)),
        "joint_angle_deg_identity": float(np.mean(base_ang)),
        "root_speed_cm_s": float(np.mean(speed)),
        "root_speed_cm_s_identity": float(np.mean(base_speed)),
        "contact_accuracy": float(np.mean(contact_acc)) if contact_acc else float("nan"),
    }


# --------------------------------------------------------------------------- driver


def train(styles: list[str] | None = None, cfg=CONFIG, out_dir: Path = WEIGHTS_DIR) -> dict:
    from models.data import build_index, warm_cache

    np.random.seed(cfg["seed"])
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    index = build_index(cfg["datasets"])
    default = sorted({c.style for c in index if c.dataset == "bandai-namco-2"} - {cfg["input_style"]})
    styles = styles or cfg["styles"] or default
    warm_cache(index)
    ref = reference_rotations(index, cfg)
    match_mean, match_std = matching_stats(index, ref, cfg)
    plan = {s: (make_pairs(index, s, "train", cfg), make_pairs(index, s, "val", cfg)) for s in styles}
    total = sum(len(a) + len(b) + len(groups(cfg)) for a, b in plan.values())
    report = {}
    with tqdm(total=total, desc="lti train", unit="step") as bar:
        for style, (train_pairs, val_pairs) in plan.items():
            t0 = time.time()
            data = []
            for a, b in train_pairs:
                bar.set_postfix_str(f"{style} align {b.name}")
                data.append(pair_data(a, b, match_mean, match_std, ref, cfg))
                bar.update(1)
            t_align = time.time() - t0
            tr, systems = identify(data, style, ref, cfg, bar)
            val = []
            for a, b in val_pairs:
                val.append(pair_data(a, b, match_mean, match_std, ref, cfg))
                bar.update(1)
            metrics = evaluate(tr, val) if val else {"pairs": 0}
            tr.prior_mean, tr.prior_radii = style_prior(index, style, cfg)
            tr.meta = {"config": cfg}
            tr.save(out_dir / f"{style}.npz")
            report[style] = {
                **metrics,
                "train_pairs": len(train_pairs),
                "train_frames": int(sum(len(d.u) for d in data)),
                "orders": [int(s.order) for s in systems],
                "state_dim": int(sum(s.order for s in systems)),
                "spectral_radius": spectral_radius(tr.A),
                "raw_spectral_radius_max": max(s.raw_radius for s in systems),
                "blocks_with_unstable_or_capped_A": int(sum(s.n_stabilized > 0 for s in systems)),
                "eigenvalues_moved": int(sum(s.n_stabilized for s in systems)),
                "seconds": time.time() - t0,
                "align_seconds": t_align,
            }
            tqdm.write(
                f"{style}: "
                + json.dumps(
                    {k: (round(v, 4) if isinstance(v, float) else v) for k, v in report[style].items() if k != "orders"}
                )
            )
    path = out_dir / "training_report.json"
    old = json.loads(path.read_text())["styles"] if path.exists() else {}
    path.write_text(json.dumps({"config": cfg, "styles": {**old, **report}}, indent=1))
    return report
