"""The inputs the evaluation streams, one set per source, and which split each run may see.

Four sources: Bandai Namco dataset 2 (the models' data), dataset 1 (another session), CMU and Xia
(other rigs, retargeted). `make eval` ("val") sees only what no final run needs: dataset 1's
TRAIN neutral clips are its validation inputs; CMU is scored by the final run only.
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
    """Every source's inputs for `split` ("val" or "test"); `quick`: two clips each, for the tests."""
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
