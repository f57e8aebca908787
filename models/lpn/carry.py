"""The LPN training set packed small enough to travel with a device run (64 MiB in all, against
0.8 GB of cache), and unpacked there.

Samples are gathers over frames, and mirrored takes reflections, so the pack keeps per unmirrored
frame the pose features at 8 bits, root position and yaw, and for each take and its mirror the
phases, frequencies and contacts. Unpacking rebuilds every sample as the cache build does.

    .venv/bin/python -m models.lpn.carry pack .data/carry/lpn.npz     # ~33 MB, from the cache
    .venv/bin/python -m models.lpn.carry check .data/carry/lpn.npz    # unpacked vs the cache
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from ..motion.assets import bandai_namco_pose
from ..motion.bn_skeleton import BODY
from ..motion.features import WORLD_MIRROR, mirror_reflections
from . import features as lf
from .dataset import ClipFrames, DataConfig, Split, cache_dir, load_meta, load_split, load_stats, samples_from_frames

SPLITS = ("train", "val")


def _body_mirror() -> tuple[np.ndarray, np.ndarray]:
    """Each body joint's mirror and the signs its channels take (`motion.features.mirror`)."""
    sk = bandai_namco_pose().skeleton
    m = sk.mirror_map()
    s = mirror_reflections(sk)
    body = list(BODY)
    index = np.array([body.index(m[j]) for j in BODY])
    signs = np.ones((lf.NB, lf.POSE_CH))
    for b, j in enumerate(BODY):
        signs[b, 0:3] = WORLD_MIRROR
        signs[b, 3:6] = WORLD_MIRROR
        signs[b, 6:9] = WORLD_MIRROR * s[j][2]
        signs[b, 9:12] = WORLD_MIRROR * s[j][1]
    return index, signs


def mirror_frames(fr: ClipFrames, phases: np.ndarray, frequency: np.ndarray, contacts: np.ndarray) -> ClipFrames:
    """The mirror image's frames: pose and root reflected (world X), with the given phases."""
    index, signs = _body_mirror()
    return ClipFrames(fr.pose[:, index] * signs, fr.xz * np.array([-1.0, 1.0]), -fr.yaw, phases, frequency, contacts)


def _quantise(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.round((a - lo) / np.maximum(hi - lo, 1e-12) * 255).astype(np.uint8)


def _restore(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return q.astype(np.float64) / 255 * (hi - lo) + lo


def pack(out: Path, cfg: DataConfig = DataConfig()) -> Path:
    """Write the pack of the cache's train and val splits (frames rebuilt, phases as cached)."""
    from ..data import load_motions
    from .dataset import _build_split, all_styles, locomotion_clips, style_name

    clips = locomotion_clips(cfg)
    styles = all_styles(cfg)
    everything = styles + list(cfg.held_out)
    arrays: dict[str, np.ndarray] = {}
    for split in SPLITS:
        cl = [c for c in clips if c.split == split and style_name(c) in styles]
        mirrored = cfg.mirror_train and split == "train"
        frames = _build_split(cl, load_motions(cl), everything, mirrored, print, frames_only=True)
        n = len(frames["names"]) // (2 if mirrored else 1)
        own, twin = frames["frames"][:n], frames["frames"][n:]
        pose = np.concatenate([f.pose.reshape(len(f.yaw), -1) for f in own])
        lo, hi = pose.min(0), pose.max(0)
        ph = [np.concatenate([f.phases.reshape(len(f.yaw), -1) for f in part]) for part in (own, twin) if part]
        fq = [np.concatenate([f.frequency for f in part]) for part in (own, twin) if part]
        ct = [np.concatenate([f.contacts for f in part]) for part in (own, twin) if part]
        plo, phi = min(p.min() for p in ph), max(p.max() for p in ph)
        flo, fhi = min(f.min() for f in fq), max(f.max() for f in fq)
        arrays.update(
            {
                f"{split}_pose": _quantise(pose, lo, hi),
                f"{split}_pose_range": np.stack([lo, hi]),
                f"{split}_root": np.concatenate([np.c_[f.xz, f.yaw] for f in own]).astype(np.float32),
                f"{split}_phases": np.stack([_quantise(p, plo, phi) for p in ph]),
                f"{split}_phase_range": np.array([plo, phi]),
                f"{split}_frequency": np.stack([_quantise(f, flo, fhi) for f in fq]),
                f"{split}_frequency_range": np.array([flo, fhi]),
                f"{split}_contacts": np.stack(ct).astype(np.uint8),
                f"{split}_lengths": np.array([len(f.yaw) for f in own]),
                f"{split}_style": frames["clip_style"][:n],
                f"{split}_gait": frames["gait"][:n],
                f"{split}_names": np.array(frames["names"][:n]),
            }
        )
    stats = load_stats(cfg)
    arrays.update({f"stats_{k}": v for k, v in stats.items()})
    meta = {k: v for k, v in load_meta(cfg).items() if k in ("config", "styles", "held_out")}
    arrays["meta"] = np.array(json.dumps(meta))
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, allow_pickle=False, **arrays)
    return out


def unpack(path: Path) -> tuple[dict, Split, Split, dict[str, np.ndarray]]:
    """(meta, train, val, stats) as `dataset.load_meta`, `load_split` and `load_stats` give them."""
    with np.load(path) as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(str(a["meta"]))
    splits = {}
    for split in SPLITS:
        pose = _restore(a[f"{split}_pose"], *a[f"{split}_pose_range"]).reshape(-1, lf.NB, lf.POSE_CH)
        phases = _restore(a[f"{split}_phases"], *a[f"{split}_phase_range"])
        frequency = _restore(a[f"{split}_frequency"], *a[f"{split}_frequency_range"])
        contacts, root = a[f"{split}_contacts"].astype(float), a[f"{split}_root"].astype(np.float64)
        bounds = np.r_[0, np.cumsum(a[f"{split}_lengths"])]
        variants, styles, gaits, names = [], [], [], []
        for v in range(len(phases)):  # the takes, then (train) their mirror images
            for c in range(len(bounds) - 1):
                sl = slice(bounds[c], bounds[c + 1])
                fr = ClipFrames(
                    pose[sl],
                    root[sl, :2],
                    root[sl, 2],
                    phases[0, sl].reshape(-1, 4, 2),
                    frequency[0, sl],
                    contacts[0, sl],
                )
                if v:
                    fr = mirror_frames(fr, phases[v, sl].reshape(-1, 4, 2), frequency[v, sl], contacts[v, sl])
                variants.append(fr)
                styles.append(int(a[f"{split}_style"][c]))
                gaits.append(float(a[f"{split}_gait"][c]))
                names.append(str(a[f"{split}_names"][c]) + ("-mirror" if v else ""))
        splits[split] = _split(variants, styles, gaits, names)
    stats = {k[len("stats_") :]: v for k, v in a.items() if k.startswith("stats_")}
    return meta, splits["train"], splits["val"], stats


def _split(frames: list[ClipFrames], styles: list[int], gaits: list[float], names: list[str]) -> Split:
    parts = [samples_from_frames(f, g) for f, g in zip(frames, gaits)]
    lengths = np.array([len(p.style_feats) for p in parts])
    return Split(
        np.concatenate([p.X for p in parts]),
        np.concatenate([p.G for p in parts]),
        np.concatenate([p.Y for p in parts]),
        np.concatenate([np.full(len(p.X), k) for p, k in zip(parts, styles)]),
        np.concatenate([np.full(len(p.X), i) for i, p in enumerate(parts)]),
        np.concatenate([p.style_feats for p in parts]),
        np.r_[0, np.cumsum(lengths)[:-1]],
        lengths,
        np.array(styles),
        names,
    )


def check(path: Path, cfg: DataConfig = DataConfig()) -> dict[str, float]:
    """Per split and array, the largest error of the unpacked samples, in the cache's stds."""
    meta, train, val, stats = unpack(path)
    out = {}
    for name, got in (("train", train), ("val", val)):
        want = load_split(name, cfg)
        if got.names != want.names:
            raise ValueError(f"{name}: the pack's clips are not the cache's")
        for key, scale in (("X", stats["X_std"]), ("Y", stats["Y_std"]), ("G", stats["G_scale"])):
            err = np.abs(getattr(got, key) - getattr(want, key)) / scale
            out[f"{name} {key} max"], out[f"{name} {key} mean"] = float(err.max()), float(err.mean())
    return out


def main(argv: list[str]) -> None:
    if len(argv) != 2 or argv[0] not in ("pack", "check"):
        raise SystemExit("usage: python -m models.lpn.carry pack|check PATH")
    path = Path(argv[1])
    if argv[0] == "pack":
        print(f"{pack(path)}: {path.stat().st_size / 2**20:.1f} MiB (cache {cache_dir()})")
    else:
        for k, v in check(path).items():
            print(f"{k:14s} {v:.4f}")


if __name__ == "__main__":
    main(sys.argv[1:])
