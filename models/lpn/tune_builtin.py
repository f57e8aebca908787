"""Fine-tune the built-in styles' FiLM vectors on their own TRAIN clips, the network frozen: the
generator's mean vector is an average embedding the network was never fitted to.

    nice -n 10 .venv/bin/python -m models.lpn.tune_builtin            # writes models/weights/lpn/tuned_film.npz
    nice -n 10 .venv/bin/python -m models.lpn.tune_builtin --save=false --steps=200

Runs over `lrs` x `steps` are scored on the style's VALIDATION loss only; the best vector is kept
if it beats the committed one and keeps the streamed output rotation-plausible (`GUARD_CLIPS`).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from tqdm import tqdm

from ..eval.run import DATASET, INPUT_STYLE
from ..settings import REPO_ROOT, get_settings
from ..training import parse_overrides
from .carriage import fitted_styles
from .weights import CONFIG_FILE, TUNED_FILE, read_weights

if TYPE_CHECKING:
    from .network import LPN

GUARD_CLIPS = (("walk", "run"), 2, 90)  # validation normal clips per content, frames: the rotation guard's inputs


@dataclass
class TuneConfig:
    styles: str = ""  # comma-separated built-in styles to tune; empty: every style with dataset-2 TRAIN clips
    lrs: str = "1e-3,3e-3,1e-2,3e-2"  # Adam learning rates tried, each from the committed vector
    steps: str = "400,1200"  # run lengths tried (cosine decay to 0 over each), with every learning rate
    batch: int = 256
    eval_every: int = 100  # validation loss logged along each run (the record; only the end is compared)
    w_bone: float = 1.0  # train.TrainConfig.w_bone
    dropout: bool = True
    seed: int = 0
    threads: int = 1
    guard: bool = True  # reject a tuned vector whose streamed output leaves the rotation gate (module docstring)
    weights_dir: str = str(REPO_ROOT / "models" / "weights" / "lpn")
    save: bool = True


@dataclass
class Samples:
    X: torch.Tensor  # normalised
    G: torch.Tensor
    Y: torch.Tensor
    clips: int


@dataclass
class StyleResult:
    style: str
    film: np.ndarray  # (4, H): the best vector on validation (the committed one if nothing beat it)
    val_before: float
    val_after: float
    lr: float  # 0 when kept
    steps: int
    curves: dict[str, list[float]] = field(default_factory=dict)  # per "lr/steps": val loss at 0, eval_every, ...
    within: tuple[float, float] | None = None  # guard: worst joint's share within p99, exported / tuned
    worst_joint: str = ""
    train_clips: int = 0
    val_clips: int = 0
    seconds: float = 0.0

    @property
    def improved(self) -> bool:
        return self.val_after < self.val_before

    @property
    def kept(self) -> bool:
        """Replaces the exported vector: lower validation loss, not rejected by the guard."""
        from ..eval.run import GATE_WITHIN

        return self.improved and (self.within is None or self.within[1] >= min(GATE_WITHIN, self.within[0]))

    def record(self) -> dict:
        return {
            "val_loss_before": round(self.val_before, 5),
            "val_loss_after": round(self.val_after, 5),
            "replaced": self.kept,
            **(
                {"guard_within_before": round(self.within[0], 3), "guard_within_after": round(self.within[1], 3)}
                if self.within is not None
                else {}
            ),
            **({"guard_worst_joint": self.worst_joint} if self.worst_joint else {}),
            "lr": self.lr,
            "steps": self.steps,
            "train_clips": self.train_clips,
            "val_clips": self.val_clips,
            "seconds": round(self.seconds, 1),
        }


def style_samples(style: str, split: str, net: LPN) -> Samples:
    """The style's dataset-2 locomotion clips of `split` as samples (train mirrored), cached."""
    from ..data import build_index, load_motions, select
    from .dataset import D2, D2_CONTENTS, _build_split

    cache = Path(get_settings().cache_dir) / "lpn" / "tune_builtin" / f"{style}_{split}.npz"
    if not cache.exists():
        clips = select(build_index([D2]), split=split, style=style, content=D2_CONTENTS)
        arrays = _build_split(clips, load_motions(clips), [style], split == "train", lambda _: None)
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, X=arrays["X"], G=arrays["G"], Y=arrays["Y"], clips=len(arrays["names"]))
    with np.load(cache) as z:
        return Samples(
            net.normalise_x(torch.from_numpy(z["X"])),
            net.normalise_g(torch.from_numpy(z["G"])),
            net.normalise_y(torch.from_numpy(z["Y"])),
            int(z["clips"]),
        )


def frozen_network(weights_dir: Path) -> tuple[LPN, dict[str, np.ndarray], dict]:
    """The committed weights' network (built-in vectors as exported), every parameter frozen."""
    from .network import LPN, LPNConfig

    arrays, _, config = read_weights(weights_dir, tuned=False)
    net = LPN(LPNConfig(**config["model"]))
    net.load_state_dict({k: torch.as_tensor(v) for k, v in arrays.items() if k != "style_film"})
    for p in net.parameters():
        p.requires_grad_(False)
    films = arrays["style_film"].reshape(len(config["styles"]), 4, -1)
    return net.eval(), {s: films[i] for i, s in enumerate(config["styles"])}, config


def tune_style(net: LPN, film0: np.ndarray, train: Samples, val: Samples, cfg: TuneConfig, bar: tqdm) -> StyleResult:
    from ..motion.assets import bandai_namco_pose
    from .train import body_bones, training_loss

    parents, lengths = body_bones(bandai_namco_pose().skeleton)
    lengths_t = torch.as_tensor(lengths, dtype=torch.float32)

    def val_loss(film: torch.Tensor) -> float:
        net.drop.eval()
        with torch.no_grad():
            total = 0.0
            for lo in range(0, len(val.X), 2048):
                sl = slice(lo, lo + 2048)
                loss, _, _ = training_loss(
                    net, net(val.X[sl], val.G[sl], film), val.Y[sl], parents, lengths_t, cfg.w_bone
                )
                total += float(loss) * len(val.X[sl])
        return total / len(val.X)

    t0 = time.perf_counter()
    start = torch.from_numpy(film0[None].astype(np.float32))
    before = val_loss(start)
    best = (before, start.clone(), 0.0, 0)
    curves = {}
    for lr, steps in ((float(a), int(b)) for a in cfg.lrs.split(",") for b in cfg.steps.split(",")):
        rng = np.random.default_rng(cfg.seed)
        film = torch.nn.Parameter(start.clone())
        opt = torch.optim.Adam([film], lr=lr)
        curve = [before]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            for step in range(1, steps + 1):
                opt.param_groups[0]["lr"] = lr * 0.5 * (1 + math.cos(math.pi * (step - 1) / steps))
                net.drop.train(cfg.dropout)
                idx = torch.from_numpy(rng.choice(len(train.X), cfg.batch, replace=False))
                loss, _, _ = training_loss(
                    net, net(train.X[idx], train.G[idx], film), train.Y[idx], parents, lengths_t, cfg.w_bone
                )
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                bar.update(1)
                if step % cfg.eval_every == 0 or step == steps:
                    curve.append(val_loss(film.detach()))
                    bar.set_postfix(lr=lr, train=f"{loss.item():.4f}", val=f"{curve[-1]:.4f}", before=f"{before:.4f}")
        if curve[-1] < best[0]:
            best = (curve[-1], film.detach().clone(), lr, steps)
        curves[f"{lr:g}/{steps}"] = [round(c, 5) for c in curve]
    net.drop.eval()
    return StyleResult(
        "",
        best[1][0].numpy().copy(),
        before,
        best[0],
        best[2],
        best[3],
        curves=curves,
        train_clips=train.clips,
        val_clips=val.clips,
        seconds=time.perf_counter() - t0,
    )


def rotation_guard(weights_dir: Path, results: list[StyleResult]) -> None:
    """Each improved result's `within` on GUARD_CLIPS, with the exported and the tuned vector."""
    from ..data import build_index, load_motions, select
    from ..eval.plausibility import RotationReference
    from ..eval.run import DATASET, pick_clips, stylise
    from ..stages import Pipeline
    from .runtime import STAGES, LPNModel

    todo = [r for r in results if r.improved]
    if not todo:
        return
    contents, per_content, frames = GUARD_CLIPS
    inputs = [m.slice(0, frames) for m in load_motions(pick_clips(per_content, contents, split="val"))]
    index = build_index([DATASET])
    ref = RotationReference({r.style: load_motions(select(index, split="train", style=r.style)) for r in todo})
    arrays, skeleton, config = read_weights(weights_dir, tuned=False)
    stages = Pipeline.load(STAGES, weights_dir, skeleton)
    balls = stages.without("carriage", "output_prior", "arm_coupling", "hinge_floor")  # the rotation balls alone
    model = LPNModel(arrays, skeleton, config, balls)
    for r in todo:
        k = model.styles().index(r.style)
        before = ref.plausibility(r.style, stylise(model, inputs, [k] * len(inputs)))
        films = arrays["style_film"].copy()
        films[k] = r.film  # in the built-in's own row, as `read_weights` puts it: its ball stays
        twin = LPNModel({**arrays, "style_film": films}, skeleton, config, balls)
        after = ref.plausibility(r.style, stylise(twin, inputs, [k] * len(inputs)))
        r.within, r.worst_joint = (before["min_within"], after["min_within"]), after["worst_joint"]


def save(weights_dir: Path, results: list[StyleResult], cfg: TuneConfig, seconds: float) -> None:
    """This run's styles into TUNED_FILE and config.json; untuned styles keep earlier runs' vectors."""
    tuned = {r.style for r in results}
    films: dict[str, np.ndarray] = {}
    path = weights_dir / TUNED_FILE
    if path.exists():
        with np.load(path) as z:
            films = {str(name): film for name, film in zip(z["styles"], z["film"]) if str(name) not in tuned}
    films.update({r.style: r.film for r in results if r.kept})
    np.savez(
        path,
        styles=np.array(list(films)),
        film=np.stack(list(films.values())).astype(np.float32) if films else np.zeros((0, 4, 0), np.float32),
    )
    path = weights_dir / CONFIG_FILE
    config = json.loads(path.read_text())
    record = _record_runs(config.get("tuned_film", {}))
    record["runs"].append(
        {
            "command": _command(),
            "config": {k: v for k, v in asdict(cfg).items() if k not in ("weights_dir", "save")},
            "seconds": round(seconds, 1),
        }
    )
    record["styles"] = {s: r for s, r in record["styles"].items() if s not in tuned} | {
        r.style: r.record() | {"command": _command()} for r in results
    }
    config["tuned_film"] = record
    path.write_text(json.dumps(config, indent=1))


def _record_runs(old: dict) -> dict:
    """config.json's `tuned_film`: the list of runs and the latest record per style."""
    runs, styles = list(old.get("runs", [])), dict(old.get("styles", {}))
    selection = "validation-split clips of the same style (one-frame loss); never test clips or judges"
    return {"selection": selection, "runs": runs, "styles": styles}


def _command() -> str:
    return "python -m models.lpn.tune_builtin " + " ".join(sys.argv[1:])


def main(argv: list[str]) -> list[StyleResult]:
    cfg = parse_overrides(TuneConfig(), argv)
    torch.set_num_threads(cfg.threads)
    weights_dir = Path(cfg.weights_dir)
    net, films, config = frozen_network(weights_dir)
    styles = [s for s in cfg.styles.split(",") if s] or [
        s for s in fitted_styles(list(films), DATASET) if s != INPUT_STYLE
    ]
    unknown = [s for s in styles if s not in films]
    if unknown:
        raise SystemExit(f"not built-in styles: {unknown}")
    t0 = time.perf_counter()
    results = []
    per_style = sum(int(n) for n in cfg.steps.split(",")) * len(cfg.lrs.split(","))
    bar = tqdm(total=len(styles) * per_style, desc="tune", mininterval=5, file=sys.stderr)
    for style in styles:
        bar.set_description(f"tune {style}: samples")
        train, val = style_samples(style, "train", net), style_samples(style, "val", net)
        bar.set_description(f"tune {style}")
        r = tune_style(net, films[style], train, val, cfg, bar)
        r.style = style
        results.append(r)
        tqdm.write(f"{style}: {json.dumps(r.record())} curves {json.dumps(r.curves)}", file=sys.stderr)
    bar.close()
    if cfg.guard:
        rotation_guard(weights_dir, results)
    if cfg.save:
        save(weights_dir, results, cfg, time.perf_counter() - t0)
    print(json.dumps({r.style: r.record() for r in results}, indent=1))
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
