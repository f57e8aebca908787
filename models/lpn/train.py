"""Train LPN-FiLM on Bandai Namco locomotion, nanoGPT style: the config is the dataclass below,
any field overridable on the command line as --field=value.

    .venv/bin/python -m models.lpn train --minutes=60                     # then exports models/weights/lpn
    .venv/bin/python -m models.lpn.train --resume --minutes=60 --no_export # continue run_dir/ckpt.pt
    .venv/bin/python -m models.lpn.train --export=.data/lpn/run/ckpt.pt

Each step trains one style with its FiLM from a random window of its clips; a share of rollouts
feed back the network's output (`rollout.py`). Choose snapshots by streaming (`tools.lpn_snapshots`).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .. import training
from ..settings import REPO_ROOT
from ..training import Log
from . import features as lf
from .weights import NORMALISATION

if TYPE_CHECKING:
    from ..motion.skeleton import Skeleton
    from .dataset import Split
    from .network import LPN


@dataclass
class TrainConfig:
    seed: int = 1234
    threads: int = 1  # the machine is shared; a GPU lease may take more
    device: str = "cpu"  # "cuda" on a GPU lease (`make lpn-gpu`); "auto" takes a GPU where there is one
    # bfloat16 autocast: "auto" where native (CUDA, avx512_bf16 or AMX; MODEL_CARD), "true" / "false"
    bf16: str = "auto"
    batch: int = 128  # frames per step: batch // rollout rollouts
    hidden: int = 256  # the paper's 512 is too slow and large here (MODEL_CARD)
    dropout: float = 0.3
    film_norm: bool = True  # LPNConfig.film_norm: keeps the FiLM generator's units from saturating
    # closed-loop training (`rollout.py`, `closed_share`): frames per rollout (1 = teacher forcing)
    rollout: int = 8
    closed_from: float = 0.25
    closed_to: float = 1.0
    closed_ramp: float = 0.3
    val_rollouts: int = 32  # per style, for the closed-loop validation loss
    minutes: float = 60.0  # this session's wall-clock budget
    schedule_minutes: float = 0.0  # training time the cosine spans, across resumed sessions (0: `minutes`)
    max_iters: int = 1_000_000
    lr: float = 7e-4
    lr_decay_to: float = 0.05  # cosine to this fraction of lr over the schedule
    weight_decay: float = 1e-4
    w_bone: float = 1.0
    film_eval_windows: int = 4  # windows per style for the style means during validation (the export uses 32)
    eval_every: int = 500
    eval_samples: int = 256  # per style
    ckpt_every: int = 200  # run_dir/ckpt.pt, what --resume continues
    # also keep ckpt_<iter>.pt (0: only the latest): the lowest loss is not the best controller
    snapshot_every: int = 0
    snapshot_half: bool = False  # snapshots as float16 networks (9 MB: what a device run can send back)
    run_dir: str = str(REPO_ROOT / ".data" / "lpn" / "run")
    out_dir: str = str(REPO_ROOT / "out" / "lpn")
    resume: bool = False  # continue run_dir/ckpt.pt (its settings, then these overrides) if it exists
    data: str = ""  # a packed training set (`carry.py`) instead of the cache, e.g. on a GPU lease
    export: str = ""  # path of a checkpoint to export to models/weights/lpn instead of training
    init_from: str = ""  # continue from this checkpoint's network (same data and sizes); a fresh optimiser
    # start from a weights folder's network with a fresh generator (`warm_start`, `fit_generator`)
    warm_from: str = ""
    film_fit_steps: int = 300
    no_export: bool = False


def parse_args(argv: list[str]) -> TrainConfig:
    return training.parse_overrides(TrainConfig(), argv)


# --------------------------------------------------------------------------- sampling


class StyleClips:
    """Random fixed-length windows of each style's clip features (short clips concatenated)."""

    def __init__(self, split: Split, frames: int, rng: np.random.Generator) -> None:
        self.s, self.frames, self.rng = split, frames, rng
        self.by_style: dict[int, np.ndarray] = {}
        for k in np.unique(split.clip_style):
            self.by_style[int(k)] = np.flatnonzero(split.clip_style == k)

    def clip(self, c: int) -> np.ndarray:
        return self.s.feats[self.s.starts[c] : self.s.starts[c] + self.s.lengths[c]]

    def window(self, style: int) -> np.ndarray:
        parts, n = [], 0
        while n < self.frames:
            part = self.clip(int(self.rng.choice(self.by_style[style])))
            parts.append(part)
            n += len(part)
        seq = np.concatenate(parts)
        start = int(self.rng.integers(0, len(seq) - self.frames + 1))
        return seq[start : start + self.frames]

    def all_windows(self, style: int, stride: int = 60, limit: int | None = None) -> np.ndarray:
        """Deterministic windows over every clip of a style (tiled); `limit` of them, evenly spread."""
        out = []
        for c in self.by_style[style]:
            f = self.clip(int(c))
            if len(f) < self.frames:
                f = np.concatenate([f] * int(math.ceil(self.frames / len(f))))
            for st in range(0, len(f) - self.frames + 1, stride):
                out.append(f[st : st + self.frames])
        if limit is not None and len(out) > limit:
            out = [out[i] for i in np.linspace(0, len(out) - 1, limit).round().astype(int)]
        return np.stack(out)


def tile_clip(feats: np.ndarray, frames: int) -> np.ndarray:
    """A clip's features repeated until at least `frames` long (the generator needs >= ~76 frames)."""
    reps = int(math.ceil(frames / max(len(feats), 1)))
    return np.concatenate([feats] * reps) if reps > 1 else feats


@torch.no_grad()
def style_films(net: LPN, clips: StyleClips, styles: list[int], limit: int | None = None) -> dict[int, torch.Tensor]:
    """Mean FiLM parameters (4, H) of each style over windows of all its clips (or `limit` of them)."""
    net.eval()
    out = {}
    for k in styles:
        w = torch.from_numpy(clips.all_windows(k, limit=limit)).to(net.X_mean.device)
        out[k] = torch.cat([net.style_film(w[i : i + 64]) for i in range(0, len(w), 64)]).mean(0)
    net.train()
    return out


# --------------------------------------------------------------------------- validation


@torch.no_grad()
def validate(net: LPN, data: Data, films: dict[int, torch.Tensor], n: int) -> dict[str, float]:
    """One-frame losses on `n` validation samples per style (held-out styles: own FiLM vs `normal`)."""
    from .network import bone_length_loss

    net.eval()
    groups = dict(traj=lf.TRAJ_OUT, pose=lf.POSE_OUT, delta=lf.DELTA_OUT, phase=lf.PHASE_OUT, contact=lf.CONTACT_OUT)
    device = net.X_mean.device

    def run(split: Split, idx: np.ndarray, film: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = net.normalise_x(torch.from_numpy(split.X[idx]).to(device))
        g = net.normalise_g(torch.from_numpy(split.G[idx]).to(device))
        y = net.normalise_y(torch.from_numpy(split.Y[idx]).to(device))
        p = net(x, g, film[None])
        return ((p - y) ** 2), net.denormalise_y(p)

    stats: dict[str, list] = {"val": [], "bone": [], **{g: [] for g in groups}}
    for k, film in films.items():
        idx = np.flatnonzero(data.val.style == k)
        if len(idx) == 0:
            continue
        idx = idx[np.linspace(0, len(idx) - 1, min(n, len(idx))).astype(int)]
        err, p = run(data.val, idx, film)
        stats["val"].append(err.mean().item())
        stats["bone"].append(bone_length_loss(p, data.parents, data.lengths).item())
        for g, sl in groups.items():
            stats[g].append(err[:, sl].mean().item())
    out = {k: float(np.mean(v)) for k, v in stats.items()}
    if data.heldout is None or data.held_clips is None:
        net.train()
        return out
    own, neutral = [], []
    for k in data.held_clips.by_style:
        idx = np.flatnonzero(data.heldout.style == k)
        idx = idx[np.linspace(0, len(idx) - 1, min(n, len(idx))).astype(int)]
        film = net.style_film(torch.from_numpy(data.held_clips.all_windows(k, limit=8)).to(device)).mean(0)
        own.append(run(data.heldout, idx, film)[0].mean().item())
        neutral.append(run(data.heldout, idx, films[data.styles.index("normal")])[0].mean().item())
    out["heldout_clip_film"], out["heldout_normal_film"] = float(np.mean(own)), float(np.mean(neutral))
    net.train()
    return out


def training_loss(
    net: LPN, pred: torch.Tensor, target: torch.Tensor, parents: np.ndarray, lengths: torch.Tensor, w_bone: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(loss, mse, bone): normalised MSE plus `w_bone` x bone loss; `finetune.py` optimises it too."""
    from .network import bone_length_loss

    mse = (pred - target).pow(2).mean()
    bone = bone_length_loss(net.denormalise_y(pred), parents, lengths)
    return mse + w_bone * bone, mse, bone


def body_bones(skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Parents of the body joints as body indices (-1 for Hips) and rest bone lengths (NB,)."""
    parents = np.array([int(skeleton.parents[j]) - 1 for j in lf.BODY])
    lengths = np.linalg.norm(skeleton.offsets[lf.BODY], axis=-1)
    return parents, lengths


# --------------------------------------------------------------------------- scheduled sampling, warm start


def samples_per_step(cfg: TrainConfig) -> int:
    return max(cfg.batch // max(cfg.rollout, 1), 1) * max(cfg.rollout, 1)


def closed_share(cfg: TrainConfig, progress: float) -> float:
    """Share of closed-loop rollouts: `closed_from` rising to `closed_to` over `closed_ramp`."""
    ramp = min(progress / cfg.closed_ramp, 1.0) if cfg.closed_ramp > 0 else 1.0
    return cfg.closed_from + (cfg.closed_to - cfg.closed_from) * ramp


def warm_start(net: LPN, weights_dir: Path, styles: list[str]) -> torch.Tensor:
    """Load a weights folder's network into `net`, fresh generator; returns its FiLM vectors (S, 4, H)."""
    from .weights import read_weights

    arrays, _, config = read_weights(weights_dir)
    if config["styles"] != styles:
        raise SystemExit(f"{weights_dir} has other styles: {config['styles']}")
    own = net.state_dict()
    kept = {k: torch.as_tensor(v) for k, v in arrays.items() if k in own and not k.startswith("film.")}
    net.load_state_dict(kept, strict=False)
    return torch.as_tensor(arrays["style_film"]).view(len(styles), 4, -1)


def fit_generator(net: LPN, clips: StyleClips, targets: torch.Tensor, steps: int, log: Log, batch: int = 8) -> None:
    """Regress the generator onto each style's vector, so a warm-started network keeps its styles."""
    dev = net.X_mean.device
    with torch.no_grad():  # the shared part in the bias at once, the per-style part learnt
        net.film.out.bias.copy_(targets.mean(0).reshape(-1).to(dev))
    opt = torch.optim.Adam(net.film.parameters(), lr=1e-3)
    for step in range(steps):
        k = step % len(targets)
        w = torch.from_numpy(np.stack([clips.window(k) for _ in range(batch)])).to(dev)
        loss = (net.style_film(w) - targets[k].to(dev)).pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if (step + 1) % 100 == 0:
            log(f"generator fit {step + 1}/{steps}: mse {loss.item():.4f}")


# --------------------------------------------------------------------------- a run


def load_config(argv: list[str]) -> tuple[TrainConfig, dict | None]:
    return training.resume_config(TrainConfig(), argv)


@dataclass
class Data:
    """The samples, windows of each style's clips, rollout starts, and the body's bones."""

    styles: list[str]
    stats: dict[str, np.ndarray]
    train: Any  # dataset.Split
    val: Any
    heldout: Any  # None: no held-out styles (or a packed set)
    train_clips: StyleClips
    held_clips: StyleClips | None
    starts: dict[int, np.ndarray]  # per style, the train samples a rollout may start at
    val_starts: dict[int, np.ndarray]
    XGY: tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # the train samples on the device
    parents: np.ndarray
    lengths: torch.Tensor

    @staticmethod
    def load(cfg: TrainConfig, device: torch.device, rng: np.random.Generator) -> Data:
        from ..motion.assets import bandai_namco_pose
        from .dataset import DataConfig, load_meta, load_split, load_stats
        from .rollout import rollout_starts

        if cfg.data:  # a packed training set (`carry.py`): no cache, no raw data needed
            from .carry import unpack

            meta, train, val, stats = unpack(Path(cfg.data))
            heldout = None
        else:
            meta = load_meta(DataConfig())
            train, val = load_split("train", DataConfig()), load_split("val", DataConfig())
            heldout = load_split("heldout", DataConfig()) if meta["heldout"]["clips"] else None
            stats = load_stats(DataConfig())
        parents, lengths = body_bones(bandai_namco_pose().skeleton)
        K = max(cfg.rollout, 1)
        return Data(
            meta["styles"],
            stats,
            train,
            val,
            heldout,
            StyleClips(train, 120, rng),
            None if heldout is None else StyleClips(heldout, 120, rng),
            rollout_starts(train.clip, train.style, K),
            rollout_starts(val.clip, val.style, K),
            (
                torch.from_numpy(train.X).to(device),
                torch.from_numpy(train.G).to(device),
                torch.from_numpy(train.Y).to(device),
            ),
            parents,
            torch.as_tensor(lengths, dtype=torch.float32, device=device),
        )


class Run:
    """The network, optimiser, schedule and RNG of a run: what a checkpoint holds."""

    def __init__(
        self, cfg: TrainConfig, ck: dict | None, data: Data, device: torch.device, rng: np.random.Generator, log: Log
    ) -> None:
        """A new network, restored from `ck`, or started from `init_from` or `warm_from`."""
        from .network import LPN, LPNConfig

        self.cfg, self.rng, self.styles, self.data = cfg, rng, data.styles, data
        bf16 = training.use_bf16(cfg.bf16, device)
        self.autocast = training.autocast(device, bf16)
        self.mcfg = LPNConfig(hidden=cfg.hidden, dropout=cfg.dropout, film_norm=cfg.film_norm)
        self.net = LPN(self.mcfg, data.stats)
        warm_films = None
        if ck is not None:
            self.net.load_state_dict(ck["model"])
        elif cfg.init_from:
            init = torch.load(cfg.init_from, map_location="cpu", weights_only=False)
            if init["styles"] != self.styles:
                raise SystemExit(f"{cfg.init_from} was trained on other styles: {init['styles']}")
            self.net.load_state_dict(init["model"])
        elif cfg.warm_from:
            warm_films = warm_start(self.net, Path(cfg.warm_from), self.styles)
        self.net.to(device)
        log(f"config {json.dumps(asdict(cfg))}; device {device}, bfloat16 {bf16}; resumed {ck is not None}")
        log(
            f"data: train {len(data.train.X)} samples / {len(data.train.names)} clips, val {len(data.val.X)}, "
            f"heldout {0 if data.heldout is None else len(data.heldout.X)}; "
            f"{len(self.styles)} styles; parameters {sum(p.numel() for p in self.net.parameters())}"
        )
        if warm_films is not None and cfg.film_fit_steps:
            fit_generator(self.net, data.train_clips, warm_films, cfg.film_fit_steps, log)
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.schedule = training.Schedule(cfg.lr_decay_to, 60 * (cfg.schedule_minutes or cfg.minutes))
        self.history: list[dict] = []
        self.it = 0
        self.order: list[int] = []  # the styles left in this cycle, popped one per step
        if ck is not None:
            self.opt.load_state_dict(ck["optimizer"])
            self.schedule = training.Schedule.resumed(
                ck["schedule"], self.schedule.total if cfg.schedule_minutes else None
            )
            training.set_rng_state(rng, ck["rng"])
            self.it, self.history, self.order = ck["iter"], ck["history"], ck.get("order") or []

    def step(self) -> dict[str, float]:
        return train_step(self.cfg, self, self.data, self.autocast)

    def report(self, terms: dict[str, float], factor: float, steps_per_s: float) -> dict:
        return dict(
            samples_per_s=round(steps_per_s * samples_per_step(self.cfg), 1),
            train_mse=terms["mse"],
            train_bone=terms["bone"],
            lr=terms["lr"],
            closed=closed_share(self.cfg, self.schedule.progress(self.it)),
        )

    def postfix(self, terms: dict[str, float]) -> dict[str, str]:
        return dict(mse=f"{terms['mse']:.4f}", bone=f"{terms['bone']:.5f}", closed=f"{terms['closed']:.2f}")

    def validate(self) -> dict:
        """One-frame validation and the closed-loop loss over `val_rollouts` rollouts per style."""
        from .rollout import rollout

        cfg, net, data = self.cfg, self.net, self.data
        films = style_films(net, data.train_clips, list(range(len(self.styles))), limit=cfg.film_eval_windows)
        v = validate(net, data, films, cfg.eval_samples)
        K, dev = max(cfg.rollout, 1), net.X_mean.device
        net.eval()
        errs = []
        with torch.no_grad():
            for k, film in films.items():
                starts = data.val_starts.get(k, ())
                if len(starts) == 0:
                    continue
                pick = np.random.default_rng(k).choice(starts, min(cfg.val_rollouts, len(starts)), replace=False)
                idx = torch.from_numpy(pick).to(dev)[:, None] + torch.arange(K, device=dev)
                X, G, Y = (torch.from_numpy(a).to(dev)[idx] for a in (data.val.X, data.val.G, data.val.Y))
                p, t = rollout(net, X, G, Y, film[None], torch.ones(len(pick), dtype=torch.bool, device=dev))
                errs.append(((p - t) ** 2).mean().item())
        net.train()
        v["val_loop"] = float(np.mean(errs)) if errs else float("nan")
        return v

    def checkpoint(self, path: Path, resumable: bool = True) -> None:
        """What `--resume` continues exactly; not `resumable`: the network alone, a snapshot."""
        model = {k: v.detach().cpu() for k, v in self.net.state_dict().items()}
        if not resumable and self.cfg.snapshot_half:
            model = {k: v.half() if v.is_floating_point() and k not in NORMALISATION else v for k, v in model.items()}
        state = {
            "model": model,
            "model_config": asdict(self.mcfg),
            "train_config": asdict(self.cfg),
            "styles": self.styles,
            "iter": self.it,
            "seconds": self.schedule.elapsed_s,
            "history": self.history,
            "argv": sys.argv,
            "optimizer": self.opt.state_dict() if resumable else None,
            "schedule": asdict(self.schedule) if resumable else None,
            "rng": training.rng_state(self.rng) if resumable else None,
            "order": [int(k) for k in self.order] if resumable else None,  # styles left in this cycle
        }
        training.save_checkpoint(state, path)


def train_step(cfg: TrainConfig, run: Run, data: Data, autocast: torch.autocast) -> dict[str, float]:
    """One step on one style: its FiLM from a window of its clips, rollouts, some closed-loop."""
    from .rollout import rollout

    rng, net = run.rng, run.net
    if not run.order:
        run.order = list(rng.permutation(len(run.styles)))
    k = int(run.order.pop())
    K = max(cfg.rollout, 1)
    rollouts = max(cfg.batch // K, 1)
    dev = data.lengths.device
    idx = torch.from_numpy(rng.choice(data.starts[k], rollouts)).to(dev)[:, None] + torch.arange(K, device=dev)
    window = torch.from_numpy(data.train_clips.window(k)[None]).to(dev)
    closed = torch.from_numpy(rng.random(rollouts) < closed_share(cfg, run.schedule.progress(run.it))).to(dev)
    X, G, Y = data.XGY
    with autocast:
        film = net.style_film(window).mean(0, keepdim=True)
        pred, target = rollout(net, X[idx], G[idx], Y[idx], film, closed)
    pred = pred.float().reshape(-1, pred.shape[-1])
    loss, mse, bone = training_loss(net, pred, target.reshape(pred.shape), data.parents, data.lengths, cfg.w_bone)
    run.opt.zero_grad(set_to_none=True)
    loss.backward()
    run.opt.step()
    lr = run.opt.param_groups[0]["lr"]
    return {"mse": mse.item(), "bone": bone.item(), "closed": closed.float().mean().item(), "lr": lr}


def main(argv: list[str]) -> None:
    cfg, ck = load_config(argv)
    if cfg.export:
        from .weights import export_weights

        print(export_weights(Path(cfg.export)))
        return
    device = training.seeded_device(cfg.threads, cfg.seed, cfg.device)
    rng = np.random.default_rng(cfg.seed)
    run_dir, out_dir = Path(cfg.run_dir), Path(cfg.out_dir)
    log = training.start_run(run_dir, out_dir)
    data = Data.load(cfg, device, rng)
    run = Run(cfg, ck, data, device, rng, log)
    steps_per_s = training.train(run, cfg, [(run.opt, cfg.lr)], log, "lpn")
    if cfg.snapshot_every:
        run.checkpoint(run_dir / f"ckpt_{run.it:06d}.pt", resumable=False)
    log(
        f"done: {run.it} iterations, {run.schedule.elapsed_s / 60:.1f} min of training; this session "
        f"{steps_per_s * samples_per_step(cfg):.0f} samples/s"
    )
    if not cfg.no_export:
        from .weights import export_weights

        log(f"exported to {export_weights(run_dir / 'ckpt.pt')}")
        render_progress(run_dir, out_dir, "final", log)


def render_progress(run_dir: Path, out_dir: Path, tag: str, log: Log) -> None:
    """Validation render: the exported model driven by a short scripted control sequence."""
    try:
        from tools.lpn_demo import render_demo

        log(f"render {render_demo(out_dir, tag=tag, seconds=12.0, styles=('normal', 'elderly'))}")
    except Exception as exc:  # a render must never stop a training run
        log(f"render skipped: {exc!r}")


if __name__ == "__main__":
    main(sys.argv[1:])
