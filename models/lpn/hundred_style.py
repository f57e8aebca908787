"""Loader for the 100STYLE layout (Mason, Starke & Komura 2022), so users who have the data can
train LPN-FiLM on it: `{root}/{Style}/{Style}_{Gait}.bvh` and `{root}/Frame_Cuts.csv`. Takes are
cut to their frame range, then resampled or retargeted to the model's skeleton and rate.
"""

from __future__ import annotations

import csv
import hashlib
from dataclasses import dataclass
from pathlib import Path

from ..data import Clip, DataError
from ..motion.bn_skeleton import BN_JOINTS
from ..motion.resample import resample
from ..motion.retarget import retarget
from ..motion.skeleton import Motion, load

DATASET = "100style"
# gait code -> content name (running contents count as gait 1 in `dataset.gait_of`)
GAITS = {
    "FW": "walk",
    "BW": "walk-back",
    "SW": "walk-side",
    "FR": "run",
    "BR": "run-back",
    "SR": "run-side",
    "ID": "idle",
    "TR1": "transition-1",
    "TR2": "transition-2",
    "TR3": "transition-3",
}
LOCOMOTION = ("FW", "BW", "SW", "FR", "BR", "SR")
CUTS_FILE = "Frame_Cuts.csv"


@dataclass(frozen=True)
class Take:
    style: str
    gait: str  # key of GAITS
    path: Path
    start: int  # first frame kept
    stop: int  # last frame kept (inclusive)

    @property
    def name(self) -> str:
        return f"{self.style}_{self.gait}"


def read_frame_cuts(root: Path) -> dict[tuple[str, str], tuple[int, int]]:
    """{(style, gait): (start, stop)} for every range given (N/A and empty cells are skipped)."""
    path = Path(root) / CUTS_FILE
    if not path.exists():
        raise DataError(f"{path} not found: a 100STYLE folder holds {CUTS_FILE} next to the style folders")
    out = {}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        if not reader.fieldnames or "STYLE_NAME" not in reader.fieldnames:
            raise DataError(f"{path}: no STYLE_NAME column (got {reader.fieldnames})")
        for row in reader:
            for gait in GAITS:
                a = (row.get(f"{gait}_START") or "").strip()
                b = (row.get(f"{gait}_STOP") or "").strip()
                if not a or not b or a.upper() == "N/A" or b.upper() == "N/A":
                    continue
                try:
                    start, stop = int(float(a)), int(float(b))
                except ValueError:
                    raise DataError(
                        f"{path}: style {row['STYLE_NAME']}, {gait}: bad frame range {a!r}..{b!r}"
                    ) from None
                if stop < start:
                    raise DataError(f"{path}: style {row['STYLE_NAME']}, {gait}: stop {stop} before start {start}")
                out[(row["STYLE_NAME"].strip(), gait)] = (start, stop)
    return out


def scan(root: Path, gaits: tuple[str, ...] = LOCOMOTION, styles: tuple[str, ...] | None = None) -> list[Take]:
    """Every take with a frame range and a file, in style then gait order. A range whose file is
    missing is an error (a half-copied dataset should not silently train on less)."""
    root = Path(root)
    takes = []
    for (style, gait), (start, stop) in sorted(read_frame_cuts(root).items()):
        if gait not in gaits or (styles is not None and style not in styles):
            continue
        path = root / style / f"{style}_{gait}.bvh"
        if not path.exists():
            raise DataError(f"{path} is listed in {CUTS_FILE} but missing")
        takes.append(Take(style, gait, path, start, stop))
    return takes


def load_take(take: Take, fps: float = 30.0) -> Motion:
    """The take's frames [start, stop] on the Bandai Namco skeleton at `fps`."""
    motion = load(take.path)
    if take.stop >= motion.num_frames:
        raise DataError(f"{take.path}: frame range {take.start}..{take.stop} beyond its {motion.num_frames} frames")
    motion = motion.slice(take.start, take.stop + 1)
    if tuple(motion.skeleton.names) == BN_JOINTS:
        return resample(motion, fps)
    return retarget(motion, fps=fps)


def load_clip(clip: Clip, fps: float = 30.0) -> Motion:
    """`load_take` for a `Clip` made by `clips` (its frame range re-read from the cuts file)."""
    root = Path(clip.path).parent.parent
    style = Path(clip.path).parent.name
    start, stop = read_frame_cuts(root)[(style, clip.take)]
    return load_take(Take(style, clip.take, Path(clip.path), start, stop), fps)


def split_of(name: str) -> str:
    """Deterministic 80/10/10 split by a hash of the take name (one take per style and gait)."""
    h = int(hashlib.sha1(name.encode()).hexdigest()[:8], 16) % 10
    return "val" if h == 0 else "test" if h == 1 else "train"


def clips(root: Path, gaits: tuple[str, ...] = LOCOMOTION) -> list[Clip]:
    """The takes as `Clip` records (style names lower-case, `Neutral` as `normal`; `frames` counts the
    kept frames of the file)."""
    out = []
    for t in scan(root, gaits):
        style = "normal" if t.style.lower() == "neutral" else t.style.lower()
        out.append(
            Clip(
                dataset=DATASET,
                name=t.name,
                path=t.path,
                style=style,
                content=GAITS[t.gait],
                take=t.gait,
                fps=30.0,
                skeleton=DATASET,
                frames=t.stop - t.start + 1,
                split=split_of(t.name),
            )
        )
    return out
