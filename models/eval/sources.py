"""The inputs the evaluation streams, one set per source, and which split each run may see.

A user's motion comes from their own capture and performer, so every run scores four sources:
Bandai Namco dataset 2 (the data the models learned), dataset 1 (another session of the same rig),
and CMU and Xia captures (other rigs at 120 fps, through the retargeter at the models' 30 fps).
Every neutral clip of a source is scored at full length, with no cap per content.

Sealing: `make eval` (split "val") sees only what no final run needs; `make eval-final` (split
"test") scores what no choice ever saw. Dataset 1 has one take of most contents, so its split's
two or three neutral clips are too few: its TRAIN neutral clips (which LTI and Style-ERD never
trained on; LPN-FiLM trained on its locomotion takes) are the validation inputs, and its
validation and test neutral clips the sealed ones. Every Xia clip is scored, its index split's
three held-out clips by the final run alone and the other six by validation; CMU's four clips are
scored only by the final run.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..data import build_index, load_motions, select
from ..motion.retarget import retarget
from ..motion.skeleton import Motion

D1, D2 = "bandai-namco-1", "bandai-namco-2"
NEUTRAL = {D1: "normal", D2: "normal"}
# which index splits of each dataset an evaluation split scores
SEEN_BY = {
    "val": {D2: ("val",), D1: ("train",), "xia": ("train",), "cmu": ()},
    "test": {D2: ("test",), D1: ("val", "test"), "xia": ("val", "test"), "cmu": ("train", "val", "test")},
}
LABELS = {D2: "dataset 2", D1: "dataset 1", "cmu": "CMU", "xia": "Xia"}


@dataclass
class Source:
    """One source's inputs on the model rig at 30 fps, with their names and contents."""

    dataset: str
    motions: list[Motion]
    names: list[str]
    contents: list[str]

    @property
    def label(self) -> str:
        return LABELS[self.dataset]


def input_sources(split: str, quick: bool = False) -> list[Source]:
    """Every source's inputs for an evaluation `split` ("val" or "test"); `quick`: two clips
    of each, for the tests."""
    if split not in SEEN_BY:
        raise ValueError(f"split must be one of {sorted(SEEN_BY)}, not {split!r}")
    index = build_index()
    out = []
    for dataset, splits in SEEN_BY[split].items():
        clips = [c for c in select(index, dataset=dataset) if c.split in splits]
        if dataset in NEUTRAL:
            clips = [c for c in clips if c.style == NEUTRAL[dataset]]
        if quick:
            clips = clips[:2]
        if not clips:
            continue
        motions = load_motions(clips)
        if dataset not in NEUTRAL:  # another rig and rate: onto the model rig at 30 fps
            motions = [retarget(m) for m in motions]
        out.append(Source(dataset, motions, [c.name for c in clips], [c.content for c in clips]))
    return out
