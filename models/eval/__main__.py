"""`python -m models.eval [--quick] [--split val]`: score identity and every committed method; write
docs/evaluation.md, docs/eval/results.json and docs/eval/grid_<style>.png (the test clips), or the
same table on the validation clips, where settings are chosen, into out/eval-val/."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from .run import evaluate


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m models.eval", description=__doc__)
    ap.add_argument("--quick", action="store_true", help="tiny subset (4 clips, 2 styles, 60 frames)")
    ap.add_argument("--per-content", type=int, default=4, help="test clips per content (default 4)")
    ap.add_argument("--frames", type=int, default=150, help="frames per clip (default 150)")
    ap.add_argument(
        "--out", type=Path, default=None, help="output folder (default docs/; out/eval-quick, out/eval-val)"
    )
    ap.add_argument("--no-grids", action="store_true")
    ap.add_argument(
        "--split",
        choices=("test", "val"),
        default="test",
        help="clips to score: test (the report, docs/) or val (what settings are chosen by, out/eval-val)",
    )
    ap.add_argument("--methods", nargs="+", default=None, help="only these methods (default: every committed one)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    r = evaluate(
        quick=a.quick,
        per_content=a.per_content,
        frames=a.frames,
        out_dir=a.out,
        grids=not a.no_grids,
        split=a.split,
        methods=tuple(a.methods) if a.methods else None,
    )
    for name, m in r["methods"].items():
        o = m["overall"]
        print(
            f"{name:9s} style {o['style_acc']:.2f}  content {o['content_acc']:.2f}  FMD {o['fmd']:.1f}  "
            f"skate {o['skate_ratio']:.2f}  path {o['path_dev_cm']:.1f} cm"
        )
    print(f"done in {r['meta']['seconds']} s")


if __name__ == "__main__":
    main()
