"""LPN-FiLM training data: Bandai Namco locomotion as per-frame (X, G, Y) samples (`features.py`),
cached as float32 arrays under `.data/lpn/<config hash>/`.

    .venv/bin/python -m models.lpn.dataset        # build (or reuse) the cache, ~2 min

Dataset 2 keeps its plain style names (those the service and evaluation use); dataset-1 styles
are prefixed `d1-` (other actors), three of them (`HELD_OUT`) kept out to test styles from a clip.
Takes are mirrored as augmentation. Gait is 1 for run and dash; local phases use per-style-and-gait
hand axes (`phases.style_axes`).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data import Clip, build_index, load_motions, select
from ..motion.features import mirror, wrap_angle
from ..motion.rotations import rotate_y
from ..motion.skeleton import Motion
from ..settings import get_settings
from . import features as lf
from .phases import Axes, local_phases, style_axes

CACHE_VERSION = 1
D1, D2 = "bandai-namco-1", "bandai-namco-2"
D1_CONTENTS = ("walk", "run", "dash", "walk-back", "walk-left", "walk-right")
D2_CONTENTS = ("walk", "walk-turn-left", "walk-turn-right", "run")
RUNNING = ("run", "dash")
D2_STYLES = ("normal", "active", "elderly", "exhausted", "feminine", "masculine", "youthful")
HELD_OUT = ("d1-giant", "d1-chimpira", "d1-proud")


@dataclass(frozen=True)
class DataConfig:
    d1_contents: tuple[str, ...] = D1_CONTENTS
    d2_contents: tuple[str, ...] = D2_CONTENTS
    held_out: tuple[str, ...] = HELD_OUT
    mirror_train: bool = True
    offsets: tuple[int, ...] = tuple(int(o) for o in lf.OFFSETS)
    version: int = CACHE_VERSION

    def key(self) -> str:
        return hashlib.sha1(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:10]


def style_name(clip: Clip) -> str:
    return clip.style if clip.dataset == D2 else f"d1-{clip.style}"


def gait_of(content: str) -> float:
    return 1.0 if content in RUNNING else 0.0


def locomotion_clips(cfg: DataConfig = DataConfig()) -> list[Clip]:
    index = build_index([D1, D2])
    return select(index, dataset=D1, content=cfg.d1_contents) + select(index, dataset=D2, content=cfg.d2_contents)


def all_styles(cfg: DataConfig = DataConfig()) -> list[str]:
    """Trained styles: the dataset-2 styles first (normal at 0), then dataset 1's minus the held-out ones."""
    d1 = sorted({style_name(c) for c in locomotion_clips(cfg) if c.dataset == D1} - set(cfg.held_out))
    return list(D2_STYLES) + d1


# --------------------------------------------------------------------------- per clip


@dataclass
class ClipSamples:
    X: np.ndarray  # (n, X_DIM)
    G: np.ndarray  # (n, G_DIM)
    Y: np.ndarray  # (n, Y_DIM)
    style_feats: np.ndarray  # (F, STYLE_DIM) every frame of the clip, for the FiLM generator


@dataclass
class ClipFrames:
    """A clip's per-frame quantities, of which every sample is a gather (what `carry.py` packs)."""

    pose: np.ndarray  # (F, NB, 12) pose features in the character frame
    xz: np.ndarray  # (F, 2) world ground position of the Hips
    yaw: np.ndarray  # (F,) facing yaw
    phases: np.ndarray  # (F, 4, 2) local phase features
    frequency: np.ndarray  # (F, 4) Hz
    contacts: np.ndarray  # (F, 2) 0/1


def clip_frames(motion: Motion, axes: Axes | None = None) -> ClipFrames:
    grot, gpos = motion.global_transforms()
    w = lf.clip_frames(grot, gpos, motion.skeleton, motion.fps)
    yaw, root, vel = w["yaw"], w["root"], w["vel"]
    lp = local_phases(motion, axes)
    pose = lf.pose_features(gpos, vel, grot, root, yaw)
    return ClipFrames(pose, root[:, [0, 2]], yaw, lp.features, lp.frequency, lp.contacts.astype(float))


def clip_samples(motion: Motion, gait: float, axes: Axes | None = None) -> ClipSamples:
    """Every frame with a full future as a sample; history before the clip repeats its first frame."""
    return samples_from_frames(clip_frames(motion, axes), gait, motion.fps)


def samples_from_frames(fr: ClipFrames, gait: float, fps: float = lf.FPS) -> ClipSamples:
    F = len(fr.yaw)
    xz, yaw, pose = fr.xz, fr.yaw, fr.pose
    root_vel = np.zeros_like(xz)
    root_vel[1:] = (xz[1:] - xz[:-1]) * fps  # the Hips' backward difference, as `features.clip_frames`
    dirs = lf.direction(yaw)
    feats = fr.phases.reshape(F, -1)
    t = np.arange(0, max(F - 1 - lf.FUTURE * lf.STEP, 0))
    idx = np.clip(t[:, None] + lf.OFFSETS[None], 0, F - 1)
    X = np.concatenate(
        [
            lf.trajectory_input(xz[idx], dirs[idx], root_vel[idx], np.full(idx.shape, gait), xz[t], yaw[t]),
            pose[t].reshape(len(t), -1),
        ],
        axis=1,
    )
    G = feats[idx].reshape(len(t), -1)
    t1 = t + 1
    fidx = t1[:, None] + lf.OFFSETS[None, lf.PAST + 1 :]
    y1 = -yaw[t1][:, None]  # into the next frame's character frame
    traj = np.concatenate(
        [
            rotate_y(xz[fidx] - xz[t1][:, None], y1),
            rotate_y(dirs[fidx], y1),
            rotate_y(root_vel[fidx], y1),
        ],
        axis=-1,
    ).reshape(len(t), -1)
    delta = np.concatenate([rotate_y(xz[t1] - xz[t], -yaw[t]), wrap_angle(yaw[t1] - yaw[t])[:, None]], axis=1)
    phases = feats[t1[:, None] + lf.OFFSETS[None, lf.PAST :]].reshape(len(t), -1)
    Y = np.concatenate(
        [traj, pose[t1].reshape(len(t), -1), delta, phases, fr.frequency[t1], fr.contacts[t1].astype(float)], axis=1
    )
    return ClipSamples(
        X.astype(np.float32),
        G.astype(np.float32),
        Y.astype(np.float32),
        lf.style_features(pose, root_vel, yaw, fps).astype(np.float32),
    )


STYLE_FEATURE_BLOCK = 1024  # frames per block of `clip_style_features`


def clip_style_features(motion: Motion) -> np.ndarray:
    """(F, STYLE_DIM) generator features, in blocks so no numpy call holds the GIL for long."""
    F = motion.num_frames
    if F <= STYLE_FEATURE_BLOCK:
        return _style_features_in_one_go(motion)
    blocks = []
    for start in range(0, F, STYLE_FEATURE_BLOCK):
        before = min(start, 1)
        block = _style_features_in_one_go(motion.slice(start - before, min(F, start + STYLE_FEATURE_BLOCK)))
        blocks.append(block[before:])
    return np.concatenate(blocks)


def _style_features_in_one_go(motion: Motion) -> np.ndarray:
    grot, gpos = motion.global_transforms()
    w = lf.clip_frames(grot, gpos, motion.skeleton, motion.fps)
    pose = lf.pose_features(gpos, w["vel"], grot, w["root"], w["yaw"])
    return lf.style_features(pose, w["root_vel"], w["yaw"], motion.fps).astype(np.float32)


# --------------------------------------------------------------------------- cache


@dataclass
class Split:
    X: np.ndarray
    G: np.ndarray
    Y: np.ndarray
    style: np.ndarray  # (N,) style index per sample
    clip: np.ndarray  # (N,) clip index per sample
    feats: np.ndarray  # (M, STYLE_DIM) style features of every clip, concatenated
    starts: np.ndarray  # (C,) offset of each clip in feats
    lengths: np.ndarray  # (C,)
    clip_style: np.ndarray  # (C,)
    names: list[str] = field(default_factory=list)


def cache_dir(cfg: DataConfig = DataConfig()) -> Path:
    return Path(get_settings().cache_dir) / "lpn" / cfg.key()


def _build_split(
    clips: list[Clip],
    motions: list[Motion],
    styles: list[str],
    mirror_too: bool,
    log: Callable[[str], None],
    frames_only: bool = False,
) -> dict:
    """The split's cached arrays; `frames_only`: each variant's `ClipFrames` instead (for `carry.pack`)."""
    shortest = lf.FUTURE * lf.STEP + 3  # one sample needs frame t, t + 1 and 30 frames after it
    kept = [(c, m) for c, m in zip(clips, motions) if m.num_frames >= shortest]
    if len(kept) < len(clips):
        log(f"  skipping {len(clips) - len(kept)} clips shorter than {shortest} frames")
    variants = [(c, m, False) for c, m in kept]
    if mirror_too:
        variants += [(c, mirror(m), True) for c, m in kept]
    groups: dict[tuple, list[Motion]] = defaultdict(list)
    for c, m, _ in variants:
        groups[(c.dataset, c.style, c.content)].append(m)
    axes = {k: style_axes(v) for k, v in groups.items()}
    jobs = [(m, axes[(c.dataset, c.style, c.content)]) for c, m, _ in variants]
    out: defaultdict[str, list[Any]] = defaultdict(list)
    offset = 0
    for i, ((c, m, mirrored), fr) in enumerate(zip(variants, _frames_of_every_clip(jobs))):
        k = styles.index(style_name(c))
        out["clip_style"].append(k)
        out["names"].append(c.name + ("-mirror" if mirrored else ""))
        out["gait"].append(gait_of(c.content))
        if i % 200 == 0:
            log(f"  {i}/{len(variants)} clips")
        if frames_only:
            out["frames"].append(fr)
            continue
        s = samples_from_frames(fr, gait_of(c.content), m.fps)
        out["X"].append(s.X)
        out["G"].append(s.G)
        out["Y"].append(s.Y)
        out["style"].append(np.full(len(s.X), k))
        out["clip"].append(np.full(len(s.X), i))
        out["feats"].append(s.style_feats)
        out["starts"].append(offset)
        out["lengths"].append(len(s.style_feats))
        offset += len(s.style_feats)
    if frames_only:
        return {
            "frames": out["frames"],
            "names": out["names"],
            "clip_style": np.array(out["clip_style"]),
            "gait": np.array(out["gait"]),
        }
    arrays = {k: np.concatenate(out[k]) for k in ("X", "G", "Y", "style", "clip", "feats")}
    arrays.update(
        starts=np.array(out["starts"]),
        lengths=np.array(out["lengths"]),
        clip_style=np.array(out["clip_style"]),
        names=np.array(out["names"]),
    )
    return arrays


def _clip_frames_job(job: tuple[Motion, Any]) -> ClipFrames:
    return clip_frames(*job)


def _frames_of_every_clip(jobs: Sequence[tuple[Motion, Any]]) -> Iterator[ClipFrames]:
    """`clip_frames` of every job, in order, on every core (16 on a GPU lease, 2 here)."""
    workers = min(os.cpu_count() or 1, 16)
    if workers == 1 or len(jobs) < 8:
        yield from map(_clip_frames_job, jobs)
        return
    with ProcessPoolExecutor(workers) as pool:  # the platform's default, as the parse cache's pool (loader.py)
        yield from pool.map(_clip_frames_job, jobs, chunksize=8)


def build_cache(cfg: DataConfig = DataConfig(), log: Callable[[str], None] = print) -> Path:
    out = cache_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    clips = locomotion_clips(cfg)
    styles = all_styles(cfg)
    everything = styles + list(cfg.held_out)
    parts = {
        "train": [c for c in clips if c.split == "train" and style_name(c) in styles],
        "val": [c for c in clips if c.split == "val" and style_name(c) in styles],
        "heldout": [c for c in clips if style_name(c) in cfg.held_out],
    }
    meta: dict[str, Any] = {"config": asdict(cfg), "styles": styles, "held_out": list(cfg.held_out)}
    for split, cl in parts.items():
        log(f"{split}: {len(cl)} clips")
        if not cl:
            meta[split] = {"clips": 0, "samples": 0}
            continue
        arrays = _build_split(cl, load_motions(cl), everything, cfg.mirror_train and split == "train", log)
        np.savez(out / f"{split}.npz", **arrays)
        meta[split] = {"clips": len(arrays["names"]), "samples": int(len(arrays["X"]))}
    with np.load(out / "train.npz") as z:
        stats = {}
        for key in ("X", "Y"):
            a = z[key]
            mean, std = a.mean(0), a.std(0)
            stats[f"{key}_mean"], stats[f"{key}_std"] = mean, np.maximum(std, 1e-2 * std.mean() + 1e-6)
        stats["G_scale"] = np.array(z["G"].std() + 1e-6, dtype=np.float32)
        f = z["feats"]
        stats["S_mean"], stats["S_std"] = f.mean(0), np.maximum(f.std(0), 1e-2 * f.std(0).mean() + 1e-6)
    as_float32: dict[str, Any] = {k: np.asarray(v, np.float32) for k, v in stats.items()}
    np.savez(out / "stats.npz", **as_float32)
    meta["seconds"] = round(time.time() - t0, 1)
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    log(f"cache {out} built in {meta['seconds']} s")
    return out


def _ensure(cfg: DataConfig) -> Path:
    folder = cache_dir(cfg)
    if not (folder / "meta.json").exists():
        build_cache(cfg)
    return folder


def load_split(split: str, cfg: DataConfig = DataConfig()) -> Split:
    with np.load(_ensure(cfg) / f"{split}.npz") as z:
        return Split(
            z["X"],
            z["G"],
            z["Y"],
            z["style"],
            z["clip"],
            z["feats"],
            z["starts"],
            z["lengths"],
            z["clip_style"],
            [str(n) for n in z["names"]],
        )


def load_stats(cfg: DataConfig = DataConfig()) -> dict[str, np.ndarray]:
    with np.load(_ensure(cfg) / "stats.npz") as z:
        return {k: z[k] for k in z.files}


def load_meta(cfg: DataConfig = DataConfig()) -> dict:
    return json.loads((_ensure(cfg) / "meta.json").read_text())


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(prog="python -m models.lpn.dataset", description=__doc__.split("\n\n")[0]).parse_args()
    build_cache()
