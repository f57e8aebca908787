"""Fine-tuning a new LTI style from one uploaded clip (BN skeleton, already retargeted).

Neutral dataset-2 TRAIN clips doing the same (`content_descriptor`) are cut to the upload's step
count (`step_matched`; uncut, a slow style learns to shuffle), paired and IMW-aligned as offline
training does; `train.identify` fits the systems, the last `holdout` share kept out for held-out
numbers; the rotation prior comes from the upload's frames. The service adds the result with
`LTIStyleModel.add_style`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from models.motion.rotation_ball import fit_prior
from models.motion.skeleton import Motion

from . import representation as rep
from .model import StyleTranslator
from .train import CONFIG, PairData, align, evaluate, identify, match_features, pair_from_warp, warpable

FINETUNE = dict(
    pairs=5,  # neutral clips paired with the upload
    max_frames=300,  # cap per clip (10 s at 30 fps): alignment cost grows with T * U
    holdout=0.25,  # share of the upload kept for the held-out evaluation (when long enough)
    min_train_frames=90,
    pose_weight=0.02,  # weight of the posture distance (per feature) next to the content distance
    match_steps=True,  # cut each neutral clip to the upload's step count (`step_matched`)
    prior=True,  # the rotation ball (`train.style_prior`) fitted from the uploaded clip
    rate_weight=0.1,  # IMW's charge on a warp's departures from a steady rate (`warping.imw`)
)


class FineTuneError(RuntimeError):
    """The upload cannot be turned into a style (no data, nothing comparable, too short)."""


# --------------------------------------------------------------------------- neutral data


@dataclass
class NeutralClip:
    name: str
    frames: int
    feats: np.ndarray  # (F, 67) representation features (with the model's reference rotations)
    descriptor: np.ndarray  # posture: mean and spread of the matching features
    content: np.ndarray  # `content_descriptor`


@dataclass
class NeutralBank:
    clips: list[NeutralClip]
    match_mean: np.ndarray
    match_std: np.ndarray
    desc_std: np.ndarray
    motions: dict = field(default_factory=dict)


def _descriptor(feats: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    m = match_features(feats, mean, std)
    speed = np.linalg.norm(feats[:, :2], axis=1)
    return np.concatenate([m.mean(0), m.std(0), [speed.mean(), np.abs(feats[:, 2]).mean()]])


def _box(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average with edge padding (same length as `x`)."""
    padded = np.pad(x, (width // 2, width - 1 - width // 2), mode="edge")
    return np.convolve(padded, np.full(width, 1.0 / width), mode="valid")


def content_descriptor(feats: np.ndarray, fps: float = 30.0) -> np.ndarray:
    """What a clip does, in log units (a like ratio whatever the style): speed, smoothed turning, step rate."""
    n, w = len(feats), max(int(round(fps)), 1)
    speed = float(np.linalg.norm(feats[1:, :2], axis=1).mean()) * fps / 100.0 if n > 1 else 0.0
    yaw = _box(np.cumsum(feats[:, 2]), w)
    turning = float(np.degrees(np.abs(yaw[2 * w :] - yaw[: -2 * w]).mean()) / 2.0) if n > 2 * w else 0.0
    bob = feats[:, 3] - _box(feats[:, 3], w)
    spectrum = np.abs(np.fft.rfft(bob * np.hanning(n)))
    freq = np.fft.rfftfreq(n, 1.0 / fps)
    band = (freq > 1.0) & (freq < 4.0)
    steps = float(freq[band][np.argmax(spectrum[band])]) if band.any() else 0.0
    return np.log(np.array([speed + 0.1, turning + 1.0, steps + 0.5]))


@lru_cache(maxsize=2)
def neutral_bank(ref_key: bytes) -> NeutralBank:
    """Every neutral dataset-2 training clip, featurised once per process (a few seconds)."""
    from models.data import build_index, load_motion, select

    ref = np.frombuffer(ref_key).reshape(rep.NUM_JOINTS, 4)
    clips = select(
        build_index(["bandai-namco-2"]), dataset="bandai-namco-2", style=CONFIG["input_style"], split="train"
    )
    if not clips:
        raise FineTuneError("no neutral training clips found")
    motions = {c.name: load_motion(c) for c in clips}
    feats = {c.name: rep.motion_to_features(motions[c.name], ref) for c in clips}
    allf = np.concatenate(list(feats.values()))
    mean, std = allf.mean(0), np.maximum(allf.std(0), CONFIG["match_std_floor"])
    cap = FINETUNE["max_frames"]
    out = [
        NeutralClip(
            c.name,
            c.frames,
            feats[c.name],
            _descriptor(feats[c.name], mean, std),
            content_descriptor(feats[c.name][:cap]),
        )
        for c in clips
    ]
    desc_std = np.maximum(np.std([c.descriptor for c in out], axis=0), 1e-3)
    return NeutralBank(out, mean, std, desc_std, motions)


def steps_per_second(content: np.ndarray) -> float:
    return float(np.exp(content[2])) - 0.5


def step_matched(clip: NeutralClip, frames: int, rate: float, cap: int, match: bool = True) -> int:
    """Frames of neutral `clip` holding as many steps as `frames` of the upload, within `cap`."""
    whole = min(clip.frames, cap)
    own = steps_per_second(clip.content)
    if not match or rate <= 0.0 or own <= 0.0:
        return whole
    lo, hi = warpable()
    return int(min(whole, max(frames / hi, min(frames / lo, round(frames * rate / own)))))


def nearest_neutral(bank: NeutralBank, feats: np.ndarray, k: int, frames: int, match: bool = True) -> list[NeutralClip]:
    """The k warpable neutral clips doing the most alike; posture (`pose_weight`) breaks ties."""
    lo, hi = warpable()
    d = _descriptor(feats, bank.match_mean, bank.match_std)
    content, w = content_descriptor(feats), FINETUNE["pose_weight"]
    rate, cap = steps_per_second(content), int(FINETUNE["max_frames"])
    cands = [c for c in bank.clips if lo <= frames / step_matched(c, frames, rate, cap, match) <= hi]

    def distance(c: NeutralClip) -> float:
        pose = float(np.mean(((c.descriptor - d) / bank.desc_std) ** 2))
        return float(np.sum((c.content - content) ** 2)) + w * pose

    cands.sort(key=lambda c: (distance(c), c.name))
    return cands[:k]


# --------------------------------------------------------------------------- pairs


def pairing_config(opts: dict = FINETUNE) -> dict:
    """Offline training's configuration, with IMW's charge on unsteady warps (`rate_weight`)."""
    return {**CONFIG, "imw": {**CONFIG["imw"], "rate_weight": opts["rate_weight"]}}


def pair_from_motions(
    mi: Motion, mo: Motion, match_mean: np.ndarray, match_std: np.ndarray, ref: np.ndarray, cfg: dict = CONFIG
) -> PairData:
    """`train.pair_data` on in-memory motions (no clip keys, no cache)."""
    return pair_from_warp(mi, mo, align(mi, mo, match_mean, match_std, ref, cfg), ref)


@dataclass
class FineTuneResult:
    translator: StyleTranslator
    seconds: float
    neutral_clips: list[str]
    train_frames: int
    heldout: dict | None


def fine_tune(
    motion: Motion,
    name: str,
    ref: np.ndarray,
    progress: Callable[[float, str], None] | None = None,
    opts: dict | None = None,
) -> FineTuneResult:
    """Identify a translator for the style of `motion` (BN skeleton, 30 fps) named `name`."""
    opts = {**FINETUNE, **(opts or {})}
    report = progress or (lambda p, m: None)
    t0 = time.time()
    report(0.02, "loading neutral training clips")
    bank = neutral_bank(np.ascontiguousarray(ref, dtype=np.float64).tobytes())
    cap = opts["max_frames"]
    n = motion.num_frames
    n_hold = int(n * opts["holdout"]) if n * (1 - opts["holdout"]) >= opts["min_train_frames"] + 30 else 0
    train_part = motion.slice(0, min(n - n_hold, cap))
    hold_part = motion.slice(n - n_hold, n) if n_hold else None
    feats = rep.motion_to_features(train_part, ref)
    k, match = opts["pairs"] + (1 if hold_part is not None else 0), bool(opts["match_steps"])
    neutrals = nearest_neutral(bank, feats, k, train_part.num_frames, match)
    rate = steps_per_second(content_descriptor(feats))
    if not neutrals:
        raise FineTuneError("no neutral clip of comparable length to pair the upload with")
    report(0.1, f"pairing with {', '.join(c.name for c in neutrals[: opts['pairs']])}")
    data = []
    cfg = pairing_config(opts)
    train_neutrals = neutrals[: opts["pairs"]]
    steps = len(train_neutrals) + (1 if hold_part is not None else 0) + 1
    for i, c in enumerate(train_neutrals):
        mi = bank.motions[c.name].slice(0, step_matched(c, train_part.num_frames, rate, cap, match))
        data.append(pair_from_motions(mi, train_part, bank.match_mean, bank.match_std, ref, cfg))
        report(0.1 + 0.7 * (i + 1) / steps, f"aligned {c.name}")
    # no cross-joint context: ~1,500 frames of one upload cannot identify systems with 36 inputs
    tr, _ = identify(data, name, ref, {**CONFIG, "context": None})
    if opts["prior"]:  # the style's rotation ball from its real frames (4. above)
        tr.prior_mean, tr.prior_radii = fit_prior(
            motion.rotations, CONFIG["prior_inner_q"], CONFIG["prior_outer_q"], CONFIG["prior_margin_deg"]
        )
    tr.meta = {
        "fine_tuned": True,
        "neutral_clips": [c.name for c in train_neutrals],
        "frames": int(train_part.num_frames),
    }
    report(0.1 + 0.7 * (len(train_neutrals) + 1) / steps, "identified")
    heldout: dict | None = None
    if hold_part is not None:
        c = neutrals[-1] if len(neutrals) > len(train_neutrals) else neutrals[0]
        mi = bank.motions[c.name]
        n = step_matched(c, hold_part.num_frames, rate, cap) if match else hold_part.num_frames
        mi = mi.slice(0, min(mi.num_frames, max(n, 2)))
        try:
            heldout = evaluate(tr, [pair_from_motions(mi, hold_part, bank.match_mean, bank.match_std, ref, cfg)])
        except Exception as exc:  # noqa: BLE001 - the evaluation is informative only
            heldout = {"error": str(exc)}
    report(0.95, "done identifying")
    return FineTuneResult(
        tr, time.time() - t0, [c.name for c in train_neutrals], int(sum(len(d.u) for d in data)), heldout
    )
