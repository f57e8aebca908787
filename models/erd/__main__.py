"""Style-ERD command line.

.venv/bin/python -m models.erd fit [STYLE ...] [--stages leaf_prior,...]            # refit the decoding's hinges and the stages
.venv/bin/python -m models.erd render [--styles elderly,exhausted] [--content walk]   # out/erd/*.png|gif
.venv/bin/python -m models.erd bench [--threads 1 2] [--json]                       # step time, batch 1 and 256
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..interface import FrameBatch
from ..settings import REPO_ROOT, get_settings

if TYPE_CHECKING:
    from .runtime import ERDModel

HINGES, SOURCES = "hinges", "upload_sources"  # `fit`'s steps besides the stages: the decoding's, uploads'


def _model() -> ERDModel:
    from . import load

    return load(get_settings().weights_dir / "erd")


def render(args: argparse.Namespace) -> None:
    from ..data import build_index, load_motions, select
    from ..motion.render import render_contact_sheet, render_gif

    model = _model()
    clips = select(build_index(["bandai-namco-2"]), split=args.split, style="normal", content=args.content)
    clip = clips[args.clip]
    motion = load_motions([clip])[0]
    styles = args.styles.split(",")
    out_dir = REPO_ROOT / "out" / "erd"
    outs, titles = [motion], [f"input ({clip.name})"]
    for style in styles:
        w = np.zeros(len(model.styles()))
        w[model.styles().index(style)] = args.intensity
        labels = {} if args.unlabelled else {"content": args.content, "input_style": "normal"}
        outs.append(model.stylise_stream(motion, w, **labels))
        titles.append(f"{style} x{args.intensity:g}" + (" (no labels)" if args.unlabelled else ""))
    if args.reference:  # real clips of the target styles, same content, for comparison
        index = build_index(["bandai-namco-2"])
        for style in styles:
            ref = select(index, split="train", style=style, content=args.content)[0]
            outs.append(load_motions([ref])[0])
            titles.append(f"real {style} ({ref.name})")
    tag = (
        f"{args.content}_{'_'.join(styles)}"
        + ("_nolabels" if args.unlabelled else "")
        + (f"_x{args.intensity:g}" if args.intensity != 1.0 else "")
        + ("_ref" if args.reference else "")
        + ("" if args.view == "10,-60" else f"_view{args.view.replace(',', '_')}")
    )
    elev, azim = (float(v) for v in args.view.split(","))
    view = (elev, azim)
    print(
        render_contact_sheet(
            outs, out_dir / f"erd_{tag}.png", frames=args.frames, titles=titles, view=view, panel_size=args.panel
        )
    )
    if args.gif:
        print(
            render_gif(
                outs[: 1 + len(styles)],
                out_dir / f"erd_{tag}.gif",
                titles=titles[: 1 + len(styles)],
                seconds=args.seconds,
            )
        )


def bench(args: argparse.Namespace) -> None:
    """Per-frame cost of `step_batch` at batch 1 and 256 with the threads capped (1 = as the
    service runs), for the network in float32 (served) and float64 (the reference). Floor: the
    network's matrix products alone in numpy (see models/stepbench.py)."""
    from ..stepbench import capped_threads, stepper, time_steps
    from .runtime import load

    results = []
    for threads in args.threads:
        for dtype in (np.float32, np.float64):
            model = load(get_settings().weights_dir / "erd", dtype=dtype)
            print(
                f"Style-ERD step_batch, network {np.dtype(dtype).name}, style elderly, {threads} BLAS/torch thread(s)"
            )
            for B in (1, 256):
                rng = np.random.default_rng(0)
                q = rng.normal(size=(B, 22, 4)) * 0.05 + np.array([0, 0, 0, 1.0])
                frames = FrameBatch(np.tile([[0.0, 90.0, 0.0]], (B, 1)), q / np.linalg.norm(q, axis=-1, keepdims=True))
                w = np.zeros((B, len(model.styles())))
                w[:, model.styles().index("elderly")] = 1.0
                with capped_threads(threads):
                    timing = time_steps(
                        B,
                        stepper(model, [frames], w, B),
                        _matmul_floor(model, B),
                        args.steps if B == 1 else max(args.steps // 4, 50),
                    )
                print(timing.line())
                results.append({"threads": threads, "dtype": np.dtype(dtype).name, **timing.as_dict()})
    if args.json:
        print(json.dumps(results, indent=1))


def fit(args: argparse.Namespace) -> None:
    """Refit, in this order, the decoding's hinges (`HINGES`), the declared stages
    (`stages.STAGES`) and what an upload's stages carry from (`SOURCES`), or the ones named in
    `--stages`; each from real clips on the committed model as it is then (a fit switches off the
    stages it must not see). Named styles only: a stage's file keeps its other styles. A stage
    fitted on the output of one refitted before it must be refitted too (the default does all)."""
    import time

    import torch

    from .runtime import load
    from .stages import STAGES

    torch.set_num_threads(1)
    folder = get_settings().weights_dir / "erd"
    fits = [HINGES, *(s.name for s in STAGES), SOURCES]
    names = args.stages.split(",") if args.stages else fits
    if set(names) - set(fits):
        raise SystemExit(f"unknown stages {sorted(set(names) - set(fits))}; declared: {fits}")
    for name in (n for n in fits if n in names):
        t0 = time.time()
        if name == HINGES:
            from ..motion.assets import bandai_namco_skeleton
            from ..motion.hinge import HINGE_FILE
            from .dataset import load_split, split_hinges

            path = split_hinges(load_split("train"), bandai_namco_skeleton()).save(folder / HINGE_FILE)
        elif name == SOURCES:
            from .upload_stages import SOURCES_FILE, fit_sources

            path = fit_sources(load(folder)).save(folder / SOURCES_FILE)
        else:
            spec = next(s for s in STAGES if s.name == name)
            model = load(folder)
            stage = spec.fit(model, args.styles or None)
            if args.styles and (folder / spec.file).exists() and hasattr(stage, "with_styles_of"):
                stage = spec.load(folder / spec.file, model.skeleton).with_styles_of(stage)  # type: ignore[attr-defined]
            path = stage.save(folder / spec.file)
        print(f"{name}: wrote {path} in {time.time() - t0:.0f} s", flush=True)


def _matmul_floor(model: ERDModel, B: int) -> Callable[[], None]:
    """The network's matrix products for B sessions and nothing else: encoder, every LSTM
    branch's input and hidden products, decoder, in the model's dtype."""
    dt, H, K = model.dtype, model.H, len(model.branches)
    rng = np.random.default_rng(1)
    x = rng.standard_normal((B, model.enc_in.shape[0])).astype(dt)
    hs = rng.standard_normal((K, B, 2 * H)).astype(dt)
    d_in = rng.standard_normal((B, model.dec[0][0].shape[0])).astype(dt)

    def floor() -> None:
        h = x @ model.enc_in
        for W, _ in model.enc:
            h = h @ W
        for W in model.lstm_w:
            np.matmul(hs, W)
        h = d_in
        for W, _ in model.dec:
            h = h @ W

    return floor


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m models.erd")
    sub = ap.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fit", help="refit the decoding's hinges, the stages after the network and the upload sources")
    f.add_argument("styles", nargs="*", help="only these styles (default: every style each stage fits)")
    f.add_argument("--stages", default="", help="comma-separated names (default: all, in order)")
    r = sub.add_parser("render")
    r.add_argument("--styles", default="elderly,exhausted")
    r.add_argument("--content", default="walk")
    r.add_argument("--split", default="val")
    r.add_argument("--clip", type=int, default=0)
    r.add_argument("--intensity", type=float, default=1.0)
    r.add_argument("--frames", type=int, default=8)
    r.add_argument("--seconds", type=float, default=6.0)
    r.add_argument("--unlabelled", action="store_true")
    r.add_argument("--reference", action="store_true", help="add a real training clip of each target style")
    r.add_argument("--view", default="10,-60", help="elevation,azimuth")
    r.add_argument("--panel", type=float, default=1.9)
    r.add_argument("--no-gif", dest="gif", action="store_false")
    b = sub.add_parser("bench")
    b.add_argument("--steps", type=int, default=400)
    b.add_argument(
        "--threads", type=int, nargs="+", default=[1, 2], help="BLAS/torch thread caps to run with (service: 1)"
    )
    b.add_argument("--json", action="store_true", help="also print the numbers as JSON")
    args = ap.parse_args(argv)
    {"fit": fit, "render": render, "bench": bench}[args.cmd](args)


if __name__ == "__main__":
    main()
