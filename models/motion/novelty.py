"""Unseen content kept: how far each input frame lies from anything a model was trained on, and
the smooth fade of the model's output toward the input there.

A style model only carries what its training input showed (fed a crouch, it straightens the
legs). Per body part, chain-end positions in the hips' heading frame (in leg lengths: a crouch
lowers them whoever performs it) are compared to `CENTROIDS` frames covering the model's TRAINING
input (`cover`), against thresholds from VALIDATION clips; the fade is smoothed causally and
slerps each part toward the input (compiled in `novelty_kernels.py`; these functions fit, report
and are its reference). The model keeps stepping underneath.

`python -m models.motion.novelty fit --method NAME --datasets ... [--contents ...]` writes
`models/weights/novelty/<NAME>.npz` (`make novelty` fits every method's); `report` prints fade
rates on any clip selection. The streaming stage that applies it is `novelty_stage.py`.
"""

from __future__ import annotations

import argparse
import functools
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .bn_skeleton import BN_JOINTS, HIPS, PRIMARY_CHILD, ROOT
from .novelty_kernels import KIND_LEG_END, KIND_POSITION
from .rotation_ball import split_heading
from .skeleton import Motion, Skeleton, fk

if TYPE_CHECKING:
    from ..data import Clip

FOLDER = "novelty"  # under the weights folder: <method>.npz
CENTROIDS = 512  # training frames kept per part (`cover`)
QUANTILE = 99.5  # the validation distance the fade is measured in
START = 1.25  # a part starts to fade at this many times that distance
FULL_FADE = 2.0  # ... and is fully faded at this many times it
ATTACK_FRAMES = 3.0  # time constant of each of the two smoothing poles while the fade rises (model frames)
RELEASE_FRAMES = 8.0  # ... and while it falls back
LIFT_FULL = 0.1  # lower-body weight (fade or first pole) from which the output's feet stay above the input's floor
SPEED_WEIGHT = 0.25  # feature distance (leg lengths) per leg length/s of vertical hips speed
HEIGHT_WEIGHT = 1.0  # ... and per leg length of hips height
MAX_FIT_FRAMES = 60_000  # an even subsample of the training frames keeps a fit to seconds
TRIM_CLIPS = 0.05  # validation clips left out of the threshold (by their own p99 distance)
FLOOR = 0.12  # leg lengths: the smallest threshold, how far another performer's locomotion lies
FADED = 0.5  # a frame counts as faded (reports, the evaluation) when its largest part weight exceeds this


def body_parts(parents: np.ndarray, names: tuple[str, ...] = BN_JOINTS) -> list[np.ndarray]:
    """Joint indices per part: lower body, trunk, then each other chain off the trunk (the arms)."""
    trunk, j = [], names[HIPS]
    while j in PRIMARY_CHILD:
        j = PRIMARY_CHILD[j]
        trunk.append(names.index(j))
    top = {}
    for k in range(len(names)):
        if k in (ROOT, HIPS) or k in trunk:
            continue
        a = k
        while int(parents[a]) not in trunk and int(parents[a]) != HIPS:
            a = int(parents[a])
        top[k] = (int(parents[a]), a)
    lower = [HIPS] + [k for k, (p, _) in top.items() if p == HIPS]
    chains: dict[int, list[int]] = {}
    for k, (p, a) in top.items():
        if p != HIPS:
            chains.setdefault(a, []).append(k)
    return [np.array(lower), np.array(trunk)] + [np.array(v) for _, v in sorted(chains.items())]


def feature_kinds(parents: np.ndarray, part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J,) each joint's feature kind and (J,) its chain's first joint (`KIND_POSITION`, `KIND_LEG_END`)."""
    J = len(parents)
    has_child = np.zeros(J, bool)
    has_child[[int(p) for p in parents if p >= 0]] = True
    kind, chain_root = np.zeros(J, np.int64), np.arange(J, dtype=np.int64)
    for j in range(J):
        if has_child[j] or part[j] < 0 or j == HIPS:
            continue
        kind[j] = KIND_LEG_END if part[j] == part[HIPS] else KIND_POSITION
        k = j
        while int(parents[k]) != HIPS and part[int(parents[k])] == part[j]:
            k = int(parents[k])
        chain_root[j] = k
    return kind, chain_root


def hips_motion(hips_y: np.ndarray, fps: float, leg: float) -> np.ndarray:
    """(T,) hips heights -> (T, 2) height and causal vertical speed, in leg lengths (per second)."""
    y = np.asarray(hips_y, np.float64) / leg
    v = np.zeros_like(y)
    v[1:] = np.diff(y) * fps
    return np.stack([y, v], axis=-1)


@dataclass(frozen=True)
class NoveltyReference:
    """The model rig, each joint's part, and per part its covering frames and threshold."""

    parents: np.ndarray
    bones: np.ndarray
    part: np.ndarray
    centres: np.ndarray
    starts: np.ndarray
    threshold: np.ndarray
    leg: float

    @property
    def parts(self) -> int:
        return len(self.threshold)

    @property
    def anchors(self) -> np.ndarray:
        """(parts,) the joint each part's positions are taken from (the hips, or the part's parent)."""
        out = np.empty(self.parts, np.int64)
        for p in range(self.parts):
            joints = np.flatnonzero(self.part == p)
            out[p] = HIPS if HIPS in joints else int(self.parents[joints[0]])
        return out

    def arrays(self, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The reference as `novelty_kernels.fade_step` takes it for a model at `fps`."""
        kind, chain_root = self.kinds
        table = np.ascontiguousarray(np.stack([self.parents, self.part, kind, chain_root]), np.int64)
        anchors_starts = np.concatenate([self.anchors, self.starts]).astype(np.int64)
        knobs = (self.leg, fps, HEIGHT_WEIGHT, SPEED_WEIGHT, START, FULL_FADE, ATTACK_FRAMES, RELEASE_FRAMES, LIFT_FULL)
        floats = np.concatenate([self.threshold, knobs]).astype(np.float64)
        c = np.ascontiguousarray
        return table, anchors_starts, floats, c(self.bones, np.float64), c(self.centres, np.float64)

    @functools.cached_property
    def kinds(self) -> tuple[np.ndarray, np.ndarray]:
        """`feature_kinds` of the rig and its parts."""
        return feature_kinds(self.parents, self.part)

    def features(self, rotations: np.ndarray, hips: np.ndarray) -> list[np.ndarray]:
        """Per part (N, D_p) features of rotations (N, J, 4) and `hips_motion` (N, 2) (`feature_kinds`)."""
        _, q = split_heading(rotations)
        q[:, ROOT] = (0.0, 0.0, 0.0, 1.0)
        bones = np.broadcast_to(self.bones, (*q.shape[:-1], 3)).copy()
        bones[:, [ROOT, HIPS]] = 0.0
        pos = fk(q, bones, self.parents)[1] / self.leg
        kind, chain_root = self.kinds
        out = []
        for p, anchor in enumerate(self.anchors):
            cols = [hips * (HEIGHT_WEIGHT, SPEED_WEIGHT)] if self.part[HIPS] == p else []
            for j in np.flatnonzero(self.part == p):
                if kind[j] == KIND_POSITION:
                    cols.append(pos[:, j] - pos[:, anchor])
                elif kind[j] == KIND_LEG_END:
                    reach = np.linalg.norm(pos[:, j] - pos[:, chain_root[j]], axis=1)
                    cols.append(np.stack([reach, hips[:, 0] + pos[:, j, 1] - pos[:, HIPS, 1]], axis=1))
            out.append(np.concatenate(cols, axis=1))
        return out

    def distances(self, rotations: np.ndarray, hips: np.ndarray) -> np.ndarray:
        """(N, parts) distance of each part to its nearest covering training frame."""
        feats = self.features(rotations, hips)
        out = np.empty((len(rotations), self.parts))
        for p, f in enumerate(feats):
            c = self.centres[self.starts[p] : self.starts[p + 1], : f.shape[1]]
            out[:, p] = np.sqrt(_nearest_sq(f, c))
        return out

    def target(self, distances: np.ndarray) -> np.ndarray:
        """(N, parts) distances -> fade targets: 0 up to START x threshold, smoothstep to 1 at FULL_FADE x."""
        x = np.clip((distances / self.threshold - START) / (FULL_FADE - START), 0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)

    def clip_fades(self, rotations: np.ndarray, hips_y: np.ndarray, fps: float) -> np.ndarray:
        """(T, J, 4), (T,) at the model rate -> (T, parts) smoothed fades, as the stage computes them."""
        target = self.target(self.distances(rotations, hips_motion(hips_y, fps, self.leg)))
        w1 = w2 = np.zeros(self.parts)
        out = np.empty_like(target)
        for t in range(len(target)):
            w1, w2 = smooth(w1, w2, target[t])
            out[t] = w2
        return out

    @classmethod
    def fit(
        cls,
        train: list[tuple[np.ndarray, np.ndarray]],
        val: list[tuple[np.ndarray, np.ndarray]],
        skeleton: Skeleton,
        leg: float,
        fps: float,
        seed: int = 0,
    ) -> NoveltyReference:
        """From TRAINING clips at the model rate, thresholds from VALIDATION clips."""
        parts = body_parts(skeleton.parents)
        part = np.full(skeleton.num_joints, -1)
        for p, joints in enumerate(parts):
            part[joints] = p
        rot, hips = _frames(train, fps, leg)
        pick = np.linspace(0, len(rot) - 1, min(len(rot), MAX_FIT_FRAMES)).astype(int)
        rot, hips = rot[pick], hips[pick]
        rig = (np.asarray(skeleton.parents), np.asarray(skeleton.offsets, np.float64), part)
        ref = cls(*rig, np.zeros((0, 1)), np.zeros(len(parts) + 1, int), np.ones(len(parts)), leg)
        feats = ref.features(rot, hips)
        width = max(f.shape[1] for f in feats)
        rng = np.random.default_rng(seed)
        centres = [np.pad(cover(f, CENTROIDS, rng), ((0, 0), (0, width - f.shape[1]))) for f in feats]
        starts = np.concatenate([[0], np.cumsum([len(c) for c in centres])])
        ref = cls(*rig, np.concatenate(centres), starts, np.ones(len(parts)), leg)
        return replace(ref, threshold=calibrate(ref, val, fps))

    def save(self, path: Path) -> Path:
        np.savez_compressed(
            path,
            parents=self.parents,
            bones=self.bones,
            part=self.part,
            centres=self.centres.astype(np.float32),
            starts=self.starts,
            threshold=self.threshold,
            leg=self.leg,
        )
        return path

    @classmethod
    def load(cls, path: Path) -> NoveltyReference:
        with np.load(path) as z:
            return cls(
                z["parents"].astype(np.int64),
                np.ascontiguousarray(z["bones"], np.float64),
                z["part"].astype(np.int64),
                np.ascontiguousarray(z["centres"], np.float64),
                z["starts"].astype(np.int64),
                z["threshold"].astype(np.float64),
                float(z["leg"]),
            )


def calibrate(ref: NoveltyReference, val: list[tuple[np.ndarray, np.ndarray]], fps: float) -> np.ndarray:
    """(parts,) QUANTILE distances over validation frames, the farthest TRIM_CLIPS left out; FLOOR least."""
    per_clip = [ref.distances(np.asarray(r, np.float64), hips_motion(y, fps, ref.leg)) for r, y in val]
    out = np.empty(ref.parts)
    for p in range(ref.parts):
        far = np.array([np.percentile(d[:, p], 99) for d in per_clip])
        keep = np.argsort(far)[: len(far) - int(TRIM_CLIPS * len(far))]
        out[p] = np.percentile(np.concatenate([per_clip[i][:, p] for i in keep]), QUANTILE)
    return np.maximum(out, FLOOR)


def reference_path(weights_dir: Path, method: str) -> Path:
    """A shared folder, so no method's loader (which reads its whole folder) meets another's file."""
    return Path(weights_dir) / FOLDER / f"{method}.npz"


def _frames(clips: list[tuple[np.ndarray, np.ndarray]], fps: float, leg: float) -> tuple[np.ndarray, np.ndarray]:
    rot = np.concatenate([r for r, _ in clips]).astype(np.float64)
    hips = np.concatenate([hips_motion(y, fps, leg) for _, y in clips])
    return rot, hips


def _nearest_sq(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N,) squared distance to the nearest centre, batch-independent (`rowwise.matmul_rows`)."""
    from ..rowwise import matmul_rows

    d = (x * x).sum(1)[:, None] - 2.0 * matmul_rows(np.ascontiguousarray(x), np.ascontiguousarray(c.T))
    return np.maximum(d + (c * c).sum(1)[None], 0.0).min(axis=1)


def cover(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """(k, D) rows covering x (Gonzalez's k-centre): unlike k-means, rare poses stay covered."""
    k = min(k, len(x))
    chosen = [int(rng.integers(len(x)))]
    d2 = np.sum((x - x[chosen[0]]) ** 2, axis=1)
    for _ in range(1, k):
        chosen.append(int(d2.argmax()))
        d2 = np.minimum(d2, np.sum((x - x[chosen[-1]]) ** 2, axis=1))
    return x[chosen].copy()


def smooth(w1: np.ndarray, w2: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One frame of the fade smoother (attack above, release below): (w1, w2), w2 the fade."""
    a1 = np.where(target > w1, 1.0 / ATTACK_FRAMES, 1.0 / RELEASE_FRAMES)
    w1 = w1 + a1 * (target - w1)
    a2 = np.where(w1 > w2, 1.0 / ATTACK_FRAMES, 1.0 / RELEASE_FRAMES)
    return w1, w2 + a2 * (w1 - w2)


# --------------------------------------------------------------------------- fitting and reports


def clips_of(
    datasets: list[str], contents: list[str] | None, styles: list[str] | None, split: str
) -> tuple[list[Clip], list[Motion]]:
    from ..data import build_index, load_motions

    clips = [c for c in build_index(datasets) if c.split == split]
    clips = [c for c in clips if (contents is None or c.content in contents) and (styles is None or c.style in styles)]
    return clips, load_motions(clips)


def selected(args: argparse.Namespace, split: str) -> tuple[list[Clip], list[Motion]]:
    """The clips of `split` that `fit_or_report`'s `--datasets`, `--contents` and `--styles` name."""
    listed = lambda value: value.split(",") if value else None  # noqa: E731
    return clips_of(args.datasets.split(","), listed(args.contents), listed(args.styles), split)


def on_model_rig(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """A clip as the stage sees it: on the model rig (retargeted if another) at 30 fps."""
    from .retarget import retarget

    if tuple(motion.skeleton.names) != BN_JOINTS:
        motion = retarget(motion)
    return motion.rotations, motion.translations[:, HIPS, 1]


def fit_or_report(prog: str, doc: str, argv: list[str] | None) -> argparse.Namespace:
    """The `fit` / `report` command line of a per-method reference fitted from clips."""
    p = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    for name in ("fit", "report"):
        s = sub.add_parser(name)
        s.add_argument("--method", required=True, help="the model whose reference is fitted or read (lti, erd, lpn)")
        s.add_argument("--datasets", required=True, help="comma-separated datasets (its training input)")
        s.add_argument("--contents", help="comma-separated contents (default: every one)")
        s.add_argument("--styles", help="comma-separated input styles (default: every one)")
    sub.choices["report"].add_argument("--split", default="val")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = fit_or_report("python -m models.motion.novelty", __doc__, argv)
    from ..settings import get_settings

    path = reference_path(get_settings().weights_dir, args.method)
    if args.cmd == "fit":
        from .assets import bandai_namco_skeleton
        from .features import left_leg_length

        skeleton = bandai_namco_skeleton()
        train = [on_model_rig(m) for m in selected(args, "train")[1]]
        val = [on_model_rig(m) for m in selected(args, "val")[1]]
        ref = NoveltyReference.fit(train, val, skeleton, left_leg_length(skeleton), 30.0)
        path.parent.mkdir(exist_ok=True)
        ref.save(path)
        print(f"{path}: {len(train)} train clips, {len(val)} val clips, thresholds {np.round(ref.threshold, 3)}")
        return 0
    ref = NoveltyReference.load(path)
    clips, motions = selected(args, args.split)
    by_content: dict[str, list[int]] = {}
    for clip, m in zip(clips, motions):
        rot, y = on_model_rig(m)
        w = ref.clip_fades(rot, y, 30.0).max(axis=1)
        print(f"{clip.name:50s} faded {np.mean(w > FADED):6.1%} of {len(w)} frames")
        total = by_content.setdefault(clip.content, [0, 0])
        total[0], total[1] = total[0] + int(np.sum(w > FADED)), total[1] + len(w)
    for content, (hits, n) in sorted(by_content.items()):
        print(f"{content:30s} faded {hits / n:6.1%} of {n} frames")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
