"""Choose an LPN-FiLM snapshot by what it does closed-loop, not by its one-frame loss.

Streams dataset-2 VALIDATION neutral clips through each candidate's core toward every style and
prints per style the judges' accuracies, the pace and the FiLM generator's live units (the share
of its second convolution's outputs above the ELU floor `FLOOR`, where a unit still gets gradient).

    .venv/bin/python -m tools.lpn_snapshots models/weights/lpn .data/lpn/run_loop/ckpt_003000.pt
    .venv/bin/python -m tools.lpn_snapshots --clips=20 --frames=150 --tuned=false CANDIDATE ...

A candidate is a weights folder or a training checkpoint (exported to a scratch folder first).
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from models.data import build_index, load_motions, select
from models.eval.features import clip_features
from models.eval.judges import Judges, load_judges
from models.eval.run import LOCOMOTION, stylise_toward
from models.eval.style_judge import StyleJudge, load_style_judge
from models.lpn.dataset import D2, D2_STYLES, clip_style_features
from models.lpn.train import tile_clip
from models.motion.skeleton import Motion

if TYPE_CHECKING:
    from models.lpn.network import LPN
    from models.lpn.runtime import LPNModel

FLOOR = float(np.log(0.05))  # ELU'(h) = e^h: below this a unit is flat (slope < 5 %)
WINDOW = 120


def hips_travel(motion: Motion) -> float:
    """Horizontal distance between the hips' first and last positions."""
    hips = motion.skeleton.names.index("Hips")
    path = motion.global_transforms()[1][:, hips]
    return float(np.linalg.norm((path[-1] - path[0])[[0, 2]]))


def pace(outputs: list[Motion], inputs: list[Motion]) -> float:
    """Median over clips of the output's hip travel over its input's: judge-free, 1 keeps up with
    the input, below 1 lags it."""
    return float(np.median([hips_travel(o) / max(hips_travel(i), 1e-6) for o, i in zip(outputs, inputs)]))


@dataclass
class Options:
    clips: int = 0  # validation neutral clips streamed (0 = all), spread over the contents
    frames: int = 150  # frames of each (5 s at 30 fps; 0 = whole clips)
    styles: tuple[str, ...] = tuple(s for s in D2_STYLES if s != "normal")
    tuned: bool = True  # a weights folder with its tuned style vectors (False: the generator's means)


def validation_inputs(opts: Options) -> tuple[list[Motion], list[str]]:
    """Dataset-2 validation neutral clips, every content in turn until `opts.clips` are taken."""
    clips = sorted(select(build_index([D2]), split="val", style="normal"), key=lambda c: (c.content, c.name))
    if opts.clips:
        by_content: dict[str, list] = {}
        for c in clips:
            by_content.setdefault(c.content, []).append(c)
        picked: list = []
        row = 0
        while len(picked) < opts.clips and any(row < len(v) for v in by_content.values()):
            picked += [v[row] for v in by_content.values() if row < len(v)][: opts.clips - len(picked)]
            row += 1
        clips = picked
    motions = load_motions(clips)
    if opts.frames:
        motions = [m.slice(0, min(opts.frames, m.num_frames)) for m in motions]
    return motions, [c.content for c in clips]


def style_windows(styles: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Per style, 120-frame windows (stride 60) of its real validation clips' generator features."""
    index = build_index([D2])
    out = {}
    for s in styles:
        wins = []
        for m in load_motions(select(index, split="val", style=s)):
            f = tile_clip(clip_style_features(m), WINDOW)
            wins += [f[a : a + WINDOW] for a in range(0, len(f) - WINDOW + 1, 60)]
        out[s] = np.stack(wins).astype(np.float32)
    return out


@torch.no_grad()
def live_units(net: LPN, windows: np.ndarray) -> tuple[float, float]:
    """(share above the ELU floor, share above zero) of the second convolution's pre-activations."""
    g = net.film
    h = g._act(g.conv1(net.normalise_clip(torch.from_numpy(windows)).transpose(1, 2)))
    h = g.conv2(h)
    if g.norm:
        h = F.layer_norm(h.transpose(1, 2), h.shape[1:2]).transpose(1, 2)
    return float((h > FLOOR).float().mean()), float((h > 0).float().mean())


def load_candidate(path: Path, scratch: Path, tuned: bool = True) -> LPNModel:
    """The core alone of a weights folder or of a checkpoint (exported into `scratch`)."""
    from models.lpn.runtime import LPNModel  # noqa: F811
    from models.lpn.weights import export_weights, read_weights

    if path.is_file():
        folder = scratch / path.stem
        export_weights(path, folder)
        path = folder
    return LPNModel(*read_weights(path, tuned=tuned))  # as `load(path, core_only=True)`


def evaluate(
    model: LPNModel,
    inputs: list[Motion],
    contents: list[str],
    windows: dict[str, np.ndarray],
    opts: Options,
    judge: StyleJudge,
    old: Judges,
) -> dict[str, dict]:
    outs = stylise_toward(model, inputs, list(opts.styles))
    net = model.generator()
    walks = [c in LOCOMOTION for c in contents]  # pace means something only where the input travels
    rows = {}
    for s in opts.styles:
        read = judge.predict(outs[s], D2, contents)
        got = old.predict_content([clip_features(m) for m in outs[s]])
        live, positive = live_units(net, windows[s])
        rows[s] = {
            "style": float(np.mean([r == s for r in read])),
            "walking": float(np.mean([r == s for r, w in zip(read, walks) if w])),
            "content": float(np.mean([g == c for g, c in zip(got, contents)])),
            "pace": pace([o for o, w in zip(outs[s], walks) if w], [i for i, w in zip(inputs, walks) if w]),
            "live": live,
            "above0": positive,
            "read_as": {k: read.count(k) for k in sorted(set(read))},
        }
    return rows


def main(argv: list[str]) -> None:
    from models.training import parse_overrides

    opts = parse_overrides(Options(), [a for a in argv if a.startswith("--")])
    paths = [Path(a) for a in argv if not a.startswith("--")] or [Path("models/weights/lpn")]
    torch.set_num_threads(1)
    inputs, contents = validation_inputs(opts)
    windows = style_windows(opts.styles)
    judge, old = load_style_judge(), load_judges()
    print(f"{len(inputs)} dataset-2 validation neutral clips, {opts.frames or 'all'} frames, core alone", flush=True)
    standing = sum(c not in LOCOMOTION for c in contents)
    print(f"{standing} of them stand (gestures); 'walking': the style judge on the others", flush=True)
    print(
        f"{'candidate':34s} {'style':10s} {'judge':>6s} {'walking':>8s} {'content':>8s} {'pace':>5s} {'live':>5s} "
        f"{'>0':>5s}  read as"
    )
    with tempfile.TemporaryDirectory() as scratch:
        for path in paths:
            model = load_candidate(path, Path(scratch), opts.tuned)
            rows = evaluate(model, inputs, contents, windows, opts, judge, old)
            for s, r in rows.items():
                print(
                    f"{str(path)[-34:]:34s} {s:10s} {r['style']:6.2f} {r['walking']:8.2f} {r['content']:8.2f} "
                    f"{r['pace']:5.2f} {r['live']:5.2f} {r['above0']:5.2f}  {r['read_as']}"
                )
            keys = ("style", "walking", "content", "pace", "live")
            m = {k: np.mean([r[k] for r in rows.values()]) for k in keys}
            worst = min(r["style"] for r in rows.values())
            print(
                f"{str(path)[-34:]:34s} {'MEAN':10s} {m['style']:6.2f} {m['walking']:8.2f} {m['content']:8.2f} "
                f"{m['pace']:5.2f} {m['live']:5.2f}  worst style {worst:.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main(sys.argv[1:])
