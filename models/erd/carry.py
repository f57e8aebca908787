"""The Style-ERD training set packed small enough to travel with a device run, and unpacked there.

Features are a function of local rotations and Hips translation, so the pack keeps those (each
rotation against the cache's reference, vector part in 16 bits, ~1e-4 rad; the Hips in float32),
labels and normalisation; unpacking rebuilds the features with the cache build's code.

    .venv/bin/python -m models.erd.carry pack .data/carry/erd.npz     # ~45 MB, from the raw clips
    .venv/bin/python -m models.erd.carry check .data/carry/erd.npz    # unpacked vs the cache

`models/erd/gpu_run.sh` trains on a lent GPU from it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..motion.bn_skeleton import HIPS
from ..motion.rotations import quat_inv, quat_mul
from .dataset import CONTENTS, DATASET, STYLES, Split, load_split, load_stats
from .features import FeatureMaker

SPLITS = ("train", "val")
SCALE = 32767.0


def encode(rotations: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, J, 3) int16 vector parts relative to each reference (w >= 0), and the Hips (F, 4) float32."""
    q = rotations / np.linalg.norm(rotations, axis=-1, keepdims=True)
    rel = quat_mul(quat_inv(ref)[None], q)
    rel = np.where(rel[..., 3:] < 0, -rel, rel)
    return np.round(np.clip(rel[..., :3], -1.0, 1.0) * SCALE).astype(np.int16), q[:, HIPS].astype(np.float32)


def decode(packed: np.ndarray, hips: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(F, J, 4) float64 rotations from `encode`'s output."""
    v = packed.astype(np.float64) / SCALE
    w = np.sqrt(np.clip(1.0 - (v * v).sum(-1, keepdims=True), 0.0, 1.0))
    rel = np.concatenate([v, w], axis=-1)
    rel /= np.linalg.norm(rel, axis=-1, keepdims=True)
    out = quat_mul(ref[None], rel)
    out[:, HIPS] = hips / np.linalg.norm(hips, axis=-1, keepdims=True)
    return out


def pack(out: Path, clips: dict | None = None) -> Path:
    """Write the pack of the train and val splits (the cache's clips, or `clips` split -> clips)."""
    from ..data import build_index, load_motions, select

    stats = load_stats()
    arrays: dict[str, np.ndarray] = {k: stats[k] for k in ("mean", "std", "ref")}
    for split in SPLITS:
        chosen = clips[split] if clips is not None else select(build_index([DATASET]), split=split)
        motions = load_motions(chosen)
        coded = [encode(m.rotations, stats["ref"]) for m in motions]
        arrays[f"{split}_rot"] = np.concatenate([c[0] for c in coded])
        arrays[f"{split}_hips"] = np.concatenate([c[1] for c in coded])
        arrays[f"{split}_root"] = np.concatenate([m.translations[:, 1] for m in motions]).astype(np.float32)
        arrays[f"{split}_lengths"] = np.array([len(m.rotations) for m in motions])
        arrays[f"{split}_style"] = np.array([STYLES.index(c.style) for c in chosen])
        arrays[f"{split}_content"] = np.array([CONTENTS.index(c.content) for c in chosen])
        arrays[f"{split}_names"] = np.array([c.name for c in chosen])
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, allow_pickle=False, **arrays)
    return out


def unpack(path: Path) -> tuple[dict[str, Split], dict[str, np.ndarray]]:
    """The splits (features rebuilt) and the normalisation statistics of a pack."""
    from ..motion.assets import bandai_namco_skeleton

    with np.load(path) as z:
        a = {k: z[k] for k in z.files}
    stats = {k: a[k] for k in ("mean", "std", "ref")}
    maker = FeatureMaker(bandai_namco_skeleton(), stats["ref"])
    splits = {}
    for split in SPLITS:
        lengths = a[f"{split}_lengths"]
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        rot = decode(a[f"{split}_rot"], a[f"{split}_hips"], stats["ref"])
        root = a[f"{split}_root"].astype(np.float64)
        feats = [maker.sequence(root[s : s + n], rot[s : s + n])[0].astype(np.float32) for s, n in zip(starts, lengths)]
        splits[split] = Split(
            np.concatenate(feats),
            starts,
            lengths,
            a[f"{split}_style"],
            a[f"{split}_content"],
            [str(n) for n in a[f"{split}_names"]],
        )
    return splits, stats


def check(path: Path) -> dict[str, float]:
    """Largest difference per feature block between unpacked and cached features (in their stds)."""
    from .features import CONTACT, POS, ROT, VEL

    splits, stats = unpack(path)
    out = {}
    for split in SPLITS:
        want = load_split(split)
        got = splits[split]
        assert np.array_equal(got.lengths, want.lengths) and got.names == want.names, split
        err = np.abs(got.feats - want.feats) / stats["std"]
        for tag, sl in (("rot", ROT), ("pos", POS), ("vel", VEL), ("contact", CONTACT)):
            out[f"{split}/{tag}"] = float(err[:, sl].max())
        out[f"{split}/p999"] = float(np.percentile(err, 99.9))
        out[f"{split}/contact_flips"] = float((got.feats[:, CONTACT] != want.feats[:, CONTACT]).mean())
    return out


if __name__ == "__main__":
    cmd, target = sys.argv[1], Path(sys.argv[2])
    if cmd == "pack":
        p = pack(target)
        print(p, f"{p.stat().st_size / 2**20:.1f} MiB")
    elif cmd == "check":
        for k, v in check(target).items():
            print(f"{k}: {v:.4f}")
    else:
        raise SystemExit("usage: python -m models.erd.carry pack|check PATH")
