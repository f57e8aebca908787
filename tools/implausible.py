"""`python -m tools.implausible METHOD [--styles S ...] [--source "dataset 2"] [--core]`: which
joints and contents make a method's outputs implausible.

A clip is plausible when every joint has `PLAUSIBLE_FRAMES` of its frames near a real frame of
the style, or of a content the style never performs near the input's own (`models.eval.physical`).
This streams one source's VALIDATION inputs through the method in fresh sessions, with the
reference and inputs `make eval` uses (a reference built from other clips reads differently), and
prints per style the failing clips counted by joint and by content: where a change should look.
"""

from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from models.eval.physical import PLAUSIBLE_FRAMES, Input, Reference, measure
from models.eval.sources import LABELS, Source
from models.motion.skeleton import Motion


@dataclass
class Tally:
    """One style's plausible clips of a source, and what the others fail on."""

    clips: int = 0
    plausible: int = 0
    joints: Counter = field(default_factory=Counter)  # failing joint -> clips
    contents: Counter = field(default_factory=Counter)  # content -> failing clips

    def line(self, style: str) -> str:
        top = lambda c: ", ".join(f"{k} {n}" for k, n in c.most_common(6)) or "none"  # noqa: E731
        return f"{style}: {self.plausible}/{self.clips} plausible; failing joints {top(self.joints)}; contents {top(self.contents)}"


def tally(ref: Reference, style: str, outs: list[Motion], source: Source, inputs: list[Input]) -> Tally:
    """How `outs` (one per input of `source`, toward `style`) fare on the per-clip plausibility;
    `inputs`: the source's clips measured once (`Input.of`), as the evaluation does."""
    t = Tally()
    for out, inp, content in zip(outs, inputs, source.contents):
        within = measure(ref, style, out, inp, content).within
        failing = [ref.support.joints[j] for j in np.flatnonzero(within < PLAUSIBLE_FRAMES)]
        t.clips += 1
        t.plausible += not failing
        t.joints.update(failing)
        t.contents.update([content] if failing else [])
    return t


def main(argv: list[str] | None = None) -> None:
    from models.data import build_index
    from models.eval.run import stylise_toward
    from models.eval.sealed import real_clips
    from models.eval.sources import D2, input_sources
    from models.registry import METHODS, load_model
    from models.settings import get_settings

    ap = argparse.ArgumentParser(prog="python -m tools.implausible", description=__doc__)
    ap.add_argument("method", choices=METHODS)
    ap.add_argument("--styles", nargs="+", help="default: every style the method has dataset-2 clips of")
    ap.add_argument("--source", default=LABELS[D2], choices=sorted(LABELS.values()))
    ap.add_argument("--core", action="store_true", help="the method's published core alone")
    args = ap.parse_args(argv)
    model = load_model(get_settings().weights_dir, args.method, core_only=args.core)
    if model is None:
        raise SystemExit(f"{args.method}: no committed weights")
    index = build_index([D2])
    styles = args.styles or sorted({c.style for c in index} & set(model.styles()) - {"normal"})
    ref = real_clips(index, styles, final=False, quick=False)[0]
    source = next((s for s in input_sources("val") if s.label == args.source), None)
    if source is None:
        raise SystemExit(f"{args.source}: no validation inputs")
    outs = stylise_toward(model, source.motions, styles)
    inputs = [Input.of(m, ref) for m in source.motions]
    for style in styles:
        print(tally(ref, style, outs[style], source, inputs).line(style))


if __name__ == "__main__":
    main()
