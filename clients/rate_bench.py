"""Every frame rate, measured: real captures streamed through a session at 30, 60 and 120 fps.

    python -m clients.rate_bench [--models lti erd lpn] [--styles elderly feminine] [--seconds 8] [--gifs DIR]

Per source (a CMU, a Xia and a Bandai Namco walk), rate, model and style it prints the rotation
jitter ratio (p99 rotation acceleration, output / input), the planted-foot slide (p95, leg
lengths/s) of input and output, their ratio and the output's against the real style's own walks
(dataset 2, validation: 0.11-0.15 leg lengths/s on real elderly, feminine and neutral walks; a
swing foot that stays flat near the floor reads as slide too), and the cross-correlation lag (input frames) of
the output's joint rotations behind the input's, behind the same model's own 30 fps output
(interpolated up: what the rate adaptation adds, readable where a model's output follows its
input too loosely for the first, as LPN's does), and the session's stated delay. `--hold`
measures sample-and-hold instead (what was served before), for comparison. A session is
driven in process exactly as `service.stream` drives it (`Session.model_inputs`, `hold`,
`held_output`), on the model skeleton, so nothing but the rate adaptation and the model is
measured. CMU and Xia captures (120 fps) are retargeted to the model rig once, then decimated;
the Bandai Namco capture (30 fps) is interpolated up (`models.motion.resample`), so its 60 and
120 fps inputs carry no motion the 30 fps one lacks. Jitter and slide are relative to the same
(retargeted) input, so retargeting artefacts count on both sides.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.interface import FrameBatch, StreamingModel, style_vector
from models.motion.bn_skeleton import BODY, HIPS
from models.motion.rate import output_lag
from models.motion.rate_metrics import jitter, lag_frames, planted_slide_p95
from models.motion.resample import resample
from models.motion.skeleton import Motion

RATES = (30.0, 60.0, 120.0)
SOURCES = {  # name: (dataset, clip name, start frame at the source's rate)
    "cmu": ("cmu", "131_02", 0),
    "xia": ("xia", "neutral_walk_01_000", 0),
    "bandai-namco": ("bandai-namco-2", None, 0),
}


def serve(model: StreamingModel, style: str, root: np.ndarray, rotations: np.ndarray, fps: float) -> tuple:
    """(out roots, out rotations) of a fresh session at `fps` fed (T, 3) roots and (T, J, 4)
    rotations on the model skeleton, frame by frame, one reply per frame."""
    from service.sessions import Session

    s = Session(model, "bandai-namco", fps, "binary", {style: 1.0}, model.init_state(1))
    w = style_vector(model, {style: 1.0})[None]
    roots, rots = np.zeros_like(root), np.zeros_like(rotations)
    for t in range(len(root)):
        for step_root, step_rot in s.model_inputs(root[t], rotations[t]):
            out, s.state = model.step_batch(s.state, FrameBatch(step_root[None], step_rot[None]), w)
            s.hold(out.root[0], out.rotations[0], root[t], rotations[t])
        roots[t], rots[t] = s.held_output()
    return roots, rots


def serve_held(model: StreamingModel, style: str, root: np.ndarray, rotations: np.ndarray, fps: float) -> tuple:
    """`serve` as sample-and-hold did it: the model stepped on the frames due, each frame
    answered with the latest output, its root moved on by the input's since."""
    state, w = model.init_state(1), style_vector(model, {style: 1.0})[None]
    roots, rots = np.zeros_like(root), np.zeros_like(rotations)
    clock, ratio, held = -1.0, model.fps / fps, (root[0], rotations[0], root[0])
    for t in range(len(root)):
        clock = max(0.0, 1.0 - ratio) + ratio if clock < 0 else clock + ratio
        steps = int(clock + 1e-9)
        clock -= steps
        for _ in range(steps):
            out, state = model.step_batch(state, FrameBatch(root[t : t + 1], rotations[t : t + 1]), w)
            held = (out.root[0], out.rotations[0], root[t])
        roots[t], rots[t] = held[0] + (root[t] - held[2]), held[1]
    return roots, rots


def sources(seconds: float) -> dict[str, Motion]:
    """Each source on the model rig at 120 fps (the Bandai Namco one interpolated up from 30)."""
    from models.data import build_index, load_motion, select
    from models.motion.retarget import retarget

    index, out = build_index(), {}
    for name, (dataset, clip, start) in SOURCES.items():
        if dataset.startswith("bandai"):
            found = select(index, dataset=dataset, style="normal", content="walk", split="val")[0]
        else:
            found = next(c for c in select(index, dataset=dataset) if c.name == clip)
        motion = load_motion(found)
        n = int(round(seconds * motion.fps))
        motion = motion.slice(start, start + n)
        if not dataset.startswith("bandai"):
            motion = retarget(motion, fps=motion.fps)
        out[name] = resample(motion, 120.0)
    return out


def real_slide(style: str) -> float:
    """The planted-foot slide (p95, leg lengths/s) of the style's real dataset-2 validation walks
    (the median over clips)."""
    from models.data import build_index, load_motion, select

    clips = select(build_index(["bandai-namco-2"]), style=style, content="walk", split="val")
    slides = [planted_slide_p95(m, HIPS, m.translations[:, HIPS], m.rotations) for m in map(load_motion, clips)]
    return float(np.median(slides)) if slides else math.nan


def at_rate(motion: Motion, fps: float) -> Motion:
    """The 120 fps motion at `fps`: every k-th frame where 120 / fps is a whole k (real frames),
    else interpolated (`models.motion.resample`)."""
    k = motion.fps / fps
    if abs(k - round(k)) > 1e-9:
        return resample(motion, fps)
    step = int(round(k))
    return Motion(motion.skeleton, motion.rotations[::step], motion.translations[::step], fps, motion.euler_orders)


@dataclass
class Row:
    source: str
    fps: float
    model: str
    style: str
    jitter_in: float
    jitter_out: float
    slide_in: float
    slide_out: float
    lag: float  # behind the input, frames
    lag_own: float  # behind the model's own 30 fps output, frames
    stated: float  # the stated delay, input frames
    slide_real: float = math.nan  # the real style's (`real_slide`)

    @property
    def jitter_ratio(self) -> float:
        return self.jitter_out / self.jitter_in

    @property
    def slide_ratio(self) -> float:
        return self.slide_out / self.slide_in if self.slide_in > 0 else math.inf

    @property
    def slide_real_ratio(self) -> float:
        return self.slide_out / self.slide_real if self.slide_real > 0 else math.inf


def measure(
    source: str,
    motion: Motion,
    model: StreamingModel,
    style: str,
    own: Motion,
    held: bool = False,
    gifs: Path | None = None,
    gif_seconds: float = 2.0,
) -> Row:
    """One row: `motion` (model rig, its rate) through a session; `own`: the model's own output
    at 30 fps on the same input. With `gifs`, the input and output as a GIF at the input's rate
    (a held pose or a snapping foot shows between consecutive frames)."""
    root, rot = motion.translations[:, HIPS], motion.rotations
    out_root, out_rot = (serve_held if held else serve)(model, style, root, rot, motion.fps)
    if gifs is not None:
        write_gif(
            gifs / f"{source}_{motion.fps:.0f}fps_{model.name}_{style}.gif", motion, out_root, out_rot, gif_seconds
        )
    own_rot = resample(own, motion.fps).rotations[: len(out_rot)]
    stated = output_lag(model.fps, motion.fps) * motion.fps / model.fps
    return Row(
        source,
        motion.fps,
        model.name,
        style,
        jitter(rot, motion.fps, BODY),
        jitter(out_rot, motion.fps, BODY),
        planted_slide_p95(motion, HIPS, root, rot),
        planted_slide_p95(motion, HIPS, out_root, out_rot),
        lag_frames(rot[:, BODY], out_rot[:, BODY], max_lag=int(motion.fps)),
        lag_frames(own_rot[:, BODY], out_rot[: len(own_rot), BODY], max_lag=int(motion.fps)),
        stated,
    )


def write_gif(path: Path, motion: Motion, out_root: np.ndarray, out_rot: np.ndarray, seconds: float) -> None:
    from models.motion.render import render_gif

    translations = motion.translations.copy()
    translations[:, HIPS] = out_root
    out = Motion(motion.skeleton, out_rot, translations, motion.fps, motion.euler_orders)
    render_gif([motion, out], path, fps=motion.fps, seconds=seconds, titles=["input", path.stem], dpi=80)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", nargs="+", default=["lti", "erd", "lpn"])
    p.add_argument("--styles", nargs="+", default=["elderly", "feminine"])
    p.add_argument("--sources", nargs="+", default=list(SOURCES))
    p.add_argument("--rates", nargs="+", type=float, default=list(RATES))
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--hold", action="store_true", help="measure sample-and-hold (as served before) instead")
    p.add_argument("--gifs", type=Path, help="also write oriented GIFs, input beside output, at the input's rate")
    p.add_argument("--gif-seconds", type=float, default=2.0)
    args = p.parse_args(argv)
    from models.registry import load_models
    from models.settings import get_settings

    models = load_models(get_settings().weights_dir)
    inputs = sources(args.seconds)
    print(
        f"{'source':13} {'fps':>4} {'model':5} {'style':9} {'jitter in':>10} {'out':>10} {'ratio':>6}"
        f" {'slide in':>9} {'out':>6} {'ratio':>6} {'÷real':>6} {'lag in':>6} {'own':>5} {'stated':>6}"
    )
    worst = {"jitter": 0.0, "slide": 0.0, "real": 0.0, "lag": 0.0}
    reals = {style: real_slide(style) for style in args.styles}
    for source in args.sources:
        for name in args.models:
            model = models[name]
            base = at_rate(inputs[source], model.fps)
            for style in args.styles:
                own_root, own_rot = serve(model, style, base.translations[:, HIPS], base.rotations, model.fps)
                own = Motion(base.skeleton, own_rot, base.translations, model.fps, base.euler_orders)
                for fps in args.rates:
                    motion = at_rate(inputs[source], fps)
                    r = measure(source, motion, model, style, own, args.hold, args.gifs, args.gif_seconds)
                    r.slide_real = reals[style]
                    print(
                        f"{r.source:13} {r.fps:4.0f} {r.model:5} {r.style:9} {r.jitter_in:10.0f} {r.jitter_out:10.0f}"
                        f" {r.jitter_ratio:6.2f} {r.slide_in:9.3f} {r.slide_out:6.3f} {r.slide_ratio:6.2f}"
                        f" {r.slide_real_ratio:6.2f}"
                        f" {r.lag:6.2f} {r.lag_own:5.2f} {r.stated:6.2f}",
                        flush=True,
                    )
                    worst["jitter"] = max(worst["jitter"], r.jitter_ratio)
                    worst["slide"] = max(worst["slide"], r.slide_ratio)
                    worst["real"] = max(worst["real"], r.slide_real_ratio)
                    worst["lag"] = max(worst["lag"], abs(r.lag_own) * model.fps / fps)
    print(
        f"worst: jitter ratio {worst['jitter']:.2f} (<= 1.5), slide ratio {worst['slide']:.2f} (<= 2), "
        f"slide against the real style {worst['real']:.2f} (<= 2), "
        f"lag behind the model's own output {worst['lag']:.2f} model frames (<= 1)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
