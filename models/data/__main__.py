"""`python -m models.data summary|warm|fetch|subset`: what the mocap data holds, building the parse cache,
and making the data ready (`fetch.py`: download from a mirror, check, unpack)."""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

from ..settings import get_settings
from .archives import DATASETS
from .fetch import fetch
from .index import Clip, build_index


def format_summary(clips: list[Clip]) -> str:
    out = []
    by_dataset: dict[str, list[Clip]] = defaultdict(list)
    for clip in clips:
        by_dataset[clip.dataset].append(clip)
    for name, members in by_dataset.items():
        frames = sum(c.frames for c in members)
        minutes = sum(c.seconds for c in members) / 60
        fps = sorted({c.fps for c in members})
        splits = Counter(c.split for c in members)
        out.append(
            f"== {name}  ({DATASETS[name].skeleton} skeleton, {'/'.join(f'{f:g}' for f in fps)} fps, {DATASETS[name].licence})"
        )
        out.append(
            f"   files {len(members)}  frames {frames}  minutes {minutes:.1f}  "
            f"split train/val/test {splits['train']}/{splits['val']}/{splits['test']}"
        )
        styles = sorted({c.style for c in members})
        contents = sorted({c.content for c in members})
        table = Counter((c.style, c.content) for c in members)
        width = max(len(s) for s in styles) + 1
        out.append("   " + " " * width + " ".join(contents))
        for style in styles:
            cells = " ".join(f"{table[(style, c)] or '.':>{len(c)}}" for c in contents)
            out.append(f"   {style:<{width}}{cells}")
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m models.data", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p_sum = sub.add_parser("summary", help="files, frames, minutes and a styles x contents table (takes per cell)")
    p_sum.add_argument("--dataset", action="append", choices=list(DATASETS), help="limit to these datasets")
    p_warm = sub.add_parser("warm", help="unpack and parse every file into the cache; prints the time")
    p_warm.add_argument("--dataset", action="append", choices=list(DATASETS))
    p_fetch = sub.add_parser(
        "fetch",
        help="unpack the archives into the cache (downloading missing ones with --from), once; "
        "a second run does nothing",
    )
    p_fetch.add_argument("--dataset", action="append", choices=list(DATASETS))
    p_fetch.add_argument(
        "--from",
        dest="source",
        metavar="URL",
        help="download archives the data folder lacks from URL/<archive> (checked against their known SHA-256)",
    )
    p_fetch.add_argument("--data-dir", type=Path, help="the data folder (default: STYLESTREAM_DATA_DIR)")
    p_subset = sub.add_parser(
        "subset", help="write a smaller archive of a Bandai Namco dataset: only the takes of some contents (subset.py)"
    )
    p_subset.add_argument(
        "--dataset", required=True, choices=[n for n, s in DATASETS.items() if s.skeleton == "bandai-namco"]
    )
    p_subset.add_argument("--content", default="", help="comma-separated contents to keep (default: all)")
    p_subset.add_argument("--out", type=Path, required=True, help="folder for the archive and its SHA256SUMS")
    p_subset.add_argument("--preset", type=int, default=6, choices=range(10), help="xz level (default 6)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    if args.command == "subset":
        from .subset import write_subset

        contents = tuple(c for c in args.content.split(",") if c)
        path = write_subset(args.dataset, contents, args.out, preset=args.preset)
        print(f"{path}: {path.stat().st_size / 1e6:.1f} MB, {time.perf_counter() - t0:.1f} s")
        return 0
    if args.command == "fetch":
        settings = get_settings()
        if args.data_dir is not None:
            settings = settings.model_copy(update={"data_dir": args.data_dir})
        fetch(args.dataset, settings, args.source)
        return 0
    clips = build_index(args.dataset)
    if args.command == "summary":
        print(format_summary(clips))
    else:
        from .loader import warm_cache  # torch, through the skeleton: only for this command

        parsed = warm_cache(clips)
        print(f"{len(clips)} files, {parsed} parsed, {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
