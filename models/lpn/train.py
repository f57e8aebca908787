"""Train LPN-FiLM on Bandai Namco locomotion (CPU-friendly, nanoGPT style: the config is the
dataclass below; override any field on the command line as --field=value).

    .venv/bin/python -m models.lpn train --minutes=60          # then exports models/weights/lpn
    .venv/bin/python -m models.lpn.train --export=.data/lpn/run/ckpt.pt

Every step is a minibatch of one style (cycling through the styles in a shuffled order); the
FiLM parameters come from the generator run on random 120-frame windows of that style's training
clips, so the generator learns to embed a clip and the motion network to obey it. Loss: MSE on the
normalised output plus the bone-length loss on the predicted pose. AdamW with a cosine learning
rate over the wall-clock budget; validation loss (trained styles with their mean FiLM, held-out
styles with the FiLM of their own clips vs. of `normal`) every `eval_every` steps.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..runlog import start_run
from ..settings import REPO_ROOT
from ..train_config import parse_overrides
from . import features as lf


@dataclass
class TrainConfig:
    seed: int = 1234
    threads: int = 2
    device: str = "cpu"  # "cuda" on a GPU lease (MODEL_CARD, Training); "auto" takes a GPU where there is one
    batch: int = 128
    hidden: int = 256  # 512 (the paper) runs at 1400 samples/s on 2 cores and exceeds 12 MB in float16; see MODEL_CARD
    dropout: float = 0.3
    film_norm: bool = True  # LPNConfig.film_norm: keeps the FiLM generator's units from saturating
    # std of Gaussian noise on the normalised input pose (the pose the runtime feeds back from the
    # network's own last output) and phases, so the network learns to pull a drifted pose back
    # rather than only to continue a clean one (0 = teacher forcing alone, as the committed run)
    pose_noise: float = 0.0
    noise_velocities: bool = True  # with pose_noise: also on the joints' velocities (False: positions and axes only)
    # with pose_noise: also on the phases (False: the gating sees clean phases, which set the cadence)
    noise_phases: bool = True
    minutes: float = 60.0  # wall-clock budget
    max_iters: int = 1_000_000
    lr: float = 7e-4
    lr_decay_to: float = 0.05  # cosine to this fraction of lr over the budget
    weight_decay: float = 1e-4
    w_bone: float = 1.0
    film_windows: int = 1  # windows per step whose FiLM parameters are averaged
    film_eval_windows: int = 4  # windows per style for the style means during validation (the export uses 32)
    eval_every: int = 500
    eval_samples: int = 256  # per style
    render_every: int = 0  # 0: render only at the end
    ckpt_every: int = 200
    # also keep ckpt_<iter>.pt every so many iterations (0 = only the latest): the lowest one-frame
    # validation loss is not the best closed-loop controller (MODEL_CARD, session 17), so runs keep
    # snapshots to be chosen by streaming the validation clips
    snapshot_every: int = 0
    run_dir: str = str(REPO_ROOT / ".data" / "lpn" / "run")
    out_dir: str = str(REPO_ROOT / "out" / "lpn")
    hundred_style_dir: str = ""  # train on a 100STYLE folder (hundred_style.py) instead of Bandai Namco
    export: str = ""  # path of a checkpoint to export to models/weights/lpn instead of training
    init_from: str = ""  # continue from this checkpoint's network (same data and sizes); a fresh optimiser
    no_export: bool = False


def parse_args(argv: list[str]) -> TrainConfig:
    return parse_overrides(TrainConfig(), argv)


# --------------------------------------------------------------------------- sampling


class StyleClips:
    """Random fixed-length windows of one split's clip features per style (short clips of a style are
    concatenated until long enough), for the FiLM generator."""

    def __init__(self, split, frames: int, rng: np.random.Generator):
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
        """Deterministic windows covering every clip of a style (short clips tiled): for per-style means.
        `limit` keeps that many, evenly spread (validation during training; the export uses all)."""
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
def style_films(net, clips: StyleClips, styles: list[int], limit: int | None = None) -> dict[int, torch.Tensor]:
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
def validate(
    net,
    val,
    films: dict[int, torch.Tensor],
    heldout,
    held_clips: StyleClips,
    normal_film: torch.Tensor,
    n: int,
    parents,
    lengths,
) -> dict[str, float]:
    from .network import bone_length_loss

    net.eval()
    groups = {
        "traj": lf.TRAJ_OUT,
        "pose": lf.POSE_OUT,
        "delta": lf.DELTA_OUT,
        "phase": lf.PHASE_OUT,
        "contact": lf.CONTACT_OUT,
    }

    device = net.X_mean.device

    def run(split, idx, film):
        x = net.normalise_x(torch.from_numpy(split.X[idx]).to(device))
        g = net.normalise_g(torch.from_numpy(split.G[idx]).to(device))
        y = net.normalise_y(torch.from_numpy(split.Y[idx]).to(device))
        p = net(x, g, film[None])
        return ((p - y) ** 2), net.denormalise_y(p)

    stats: dict[str, list] = {"val": [], "bone": [], **{g: [] for g in groups}}
    for k, film in films.items():
        idx = np.flatnonzero(val.style == k)
        if len(idx) == 0:
            continue
        idx = idx[np.linspace(0, len(idx) - 1, min(n, len(idx))).astype(int)]
        err, p = run(val, idx, film)
        stats["val"].append(err.mean().item())
        stats["bone"].append(bone_length_loss(p, parents, lengths).item())
        for g, sl in groups.items():
            stats[g].append(err[:, sl].mean().item())
    out = {k: float(np.mean(v)) for k, v in stats.items()}
    if heldout is None:
        net.train()
        return out
    own, neutral = [], []
    for k in held_clips.by_style:
        idx = np.flatnonzero(heldout.style == k)
        idx = idx[np.linspace(0, len(idx) - 1, min(n, len(idx))).astype(int)]
        film = net.style_film(torch.from_numpy(held_clips.all_windows(k, limit=8)).to(device)).mean(0)
        own.append(run(heldout, idx, film)[0].mean().item())
        neutral.append(run(heldout, idx, normal_film)[0].mean().item())
    out["heldout_clip_film"], out["heldout_normal_film"] = float(np.mean(own)), float(np.mean(neutral))
    net.train()
    return out


def training_loss(
    net, pred: torch.Tensor, target: torch.Tensor, parents: np.ndarray, lengths: torch.Tensor, w_bone: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The training objective (loss, mse, bone): MSE on the normalised output plus `w_bone` times the
    bone-length loss on the denormalised pose. One function, so FiLM fine-tuning (`finetune.py`)
    optimises exactly what training did."""
    from .network import bone_length_loss

    mse = (pred - target).pow(2).mean()
    bone = bone_length_loss(net.denormalise_y(pred), parents, lengths)
    return mse + w_bone * bone, mse, bone


def pose_noise_scale(cfg: TrainConfig) -> torch.Tensor:
    """(X_DIM,) standard deviation of the noise on each normalised input: `pose_noise` on the pose
    block (without the velocity channels unless `noise_velocities`), 0 on the trajectory (the control)."""
    scale = torch.zeros(lf.X_DIM)
    pose = torch.full((lf.NB, lf.POSE_CH), cfg.pose_noise)
    if not cfg.noise_velocities:
        pose[:, 3:6] = 0.0  # position, velocity, forward axis, up axis (features.pose_features)
    scale[lf.POSE_IN] = pose.flatten()
    return scale


def lr_at(cfg: TrainConfig, frac: float) -> float:
    return cfg.lr * (cfg.lr_decay_to + (1 - cfg.lr_decay_to) * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0))))


def body_bones(skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Parents of the body joints as body indices (-1 for Hips) and rest bone lengths (NB,)."""
    parents = np.array([int(skeleton.parents[j]) - 1 for j in lf.BODY])
    lengths = np.linalg.norm(skeleton.offsets[lf.BODY], axis=-1)
    return parents, lengths


# --------------------------------------------------------------------------- main


def main(argv: list[str]) -> None:
    cfg = parse_args(argv)
    if cfg.export:
        from .weights import export_weights

        print(export_weights(Path(cfg.export)))
        return
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    auto = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(auto if cfg.device == "auto" else cfg.device)
    rng = np.random.default_rng(cfg.seed)
    from ..motion.assets import bandai_namco_pose
    from .dataset import load_meta, load_split, load_stats
    from .network import LPN, LPNConfig
    from .weights import data_config

    run_dir, out_dir = Path(cfg.run_dir), Path(cfg.out_dir)
    log = start_run(run_dir, out_dir)

    data = data_config(asdict(cfg))
    meta = load_meta(data)
    styles, train, val = meta["styles"], load_split("train", data), load_split("val", data)
    heldout = load_split("heldout", data) if meta["heldout"]["clips"] else None
    stats = load_stats(data)
    skeleton = bandai_namco_pose().skeleton
    parents, lengths_np = body_bones(skeleton)
    lengths = torch.as_tensor(lengths_np, dtype=torch.float32, device=device)
    mcfg = LPNConfig(hidden=cfg.hidden, dropout=cfg.dropout, film_norm=cfg.film_norm)
    net = LPN(mcfg, stats)
    if cfg.init_from:
        ckpt = torch.load(cfg.init_from, map_location="cpu", weights_only=False)
        if ckpt["styles"] != styles:
            raise SystemExit(f"{cfg.init_from} was trained on other styles: {ckpt['styles']}")
        net.load_state_dict(ckpt["model"])
    net.to(device)
    log(f"config {json.dumps(asdict(cfg))}; device {device}")
    log(
        f"data: train {len(train.X)} samples / {len(train.names)} clips, val {len(val.X)}, "
        f"heldout {0 if heldout is None else len(heldout.X)}; "
        f"{len(styles)} styles; parameters {sum(p.numel() for p in net.parameters())}"
    )
    train_clips = StyleClips(train, 120, rng)
    held_clips = None if heldout is None else StyleClips(heldout, 120, rng)
    by_style = {k: np.flatnonzero(train.style == k) for k in range(len(styles))}
    X, G, Y = (torch.from_numpy(a).to(device) for a in (train.X, train.G, train.Y))
    noise_scale = pose_noise_scale(cfg).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    t0 = time.time()
    budget = cfg.minutes * 60
    history: list[dict] = []
    order: list[int] = []
    bar = tqdm(total=cfg.max_iters, desc="lpn", mininterval=10, file=sys.stderr)
    it = 0
    while it < cfg.max_iters and time.time() - t0 < budget:
        for group in opt.param_groups:
            group["lr"] = lr_at(cfg, (time.time() - t0) / budget)
        if not order:
            order = list(rng.permutation(len(styles)))
        k = int(order.pop())
        idx = torch.from_numpy(rng.choice(by_style[k], cfg.batch)).to(device)
        windows = torch.from_numpy(np.stack([train_clips.window(k) for _ in range(cfg.film_windows)])).to(device)
        film = net.style_film(windows).mean(0, keepdim=True)
        xn, gn = net.normalise_x(X[idx]), net.normalise_g(G[idx])
        if cfg.pose_noise:
            xn = xn + noise_scale * torch.randn_like(xn)
            if cfg.noise_phases:
                gn = gn + cfg.pose_noise * torch.randn_like(gn)
        pred = net(xn, gn, film)
        target = net.normalise_y(Y[idx])
        loss, mse, bone = training_loss(net, pred, target, parents, lengths, cfg.w_bone)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        it += 1
        bar.update(1)
        if it % 50 == 0:
            bar.set_postfix(mse=f"{mse.item():.4f}", bone=f"{bone.item():.5f}")
        if it % cfg.eval_every == 0:
            films = style_films(net, train_clips, list(range(len(styles))), limit=cfg.film_eval_windows)
            v = validate(
                net, val, films, heldout, held_clips, films[styles.index("normal")], cfg.eval_samples, parents, lengths
            )
            v.update(
                iter=it,
                minutes=round((time.time() - t0) / 60, 2),
                train_mse=mse.item(),
                train_bone=bone.item(),
                lr=opt.param_groups[0]["lr"],
            )
            history.append(v)
            log("val " + " ".join(f"{a}={b:.4g}" if isinstance(b, float) else f"{a}={b}" for a, b in v.items()))
        if it % cfg.ckpt_every == 0:
            save(run_dir / "ckpt.pt", net, mcfg, cfg, styles, it, time.time() - t0, history)
        if cfg.snapshot_every and it % cfg.snapshot_every == 0:
            save(run_dir / f"ckpt_{it:06d}.pt", net, mcfg, cfg, styles, it, time.time() - t0, history)
        if cfg.render_every and it % cfg.render_every == 0:
            render_progress(run_dir, out_dir, f"it{it:06d}", log)
    bar.close()
    films = style_films(net, train_clips, list(range(len(styles))), limit=cfg.film_eval_windows)
    v = validate(
        net, val, films, heldout, held_clips, films[styles.index("normal")], cfg.eval_samples, parents, lengths
    )
    v.update(iter=it, minutes=round((time.time() - t0) / 60, 2))
    history.append(v)
    log("final val " + " ".join(f"{a}={b:.4g}" for a, b in v.items()))
    save(run_dir / "ckpt.pt", net, mcfg, cfg, styles, it, time.time() - t0, history)
    log(f"done: {it} iterations in {(time.time() - t0) / 60:.1f} min")
    if not cfg.no_export:
        from .weights import export_weights

        log(f"exported to {export_weights(run_dir / 'ckpt.pt')}")
        render_progress(run_dir, out_dir, "final", log)


def render_progress(run_dir: Path, out_dir: Path, tag: str, log) -> None:
    """Validation render: the exported model driven by a short scripted control sequence."""
    try:
        from .demo import render_demo

        log(f"render {render_demo(out_dir, tag=tag, seconds=12.0, styles=('normal', 'elderly'))}")
    except Exception as exc:  # a render must never stop a training run
        log(f"render skipped: {exc!r}")


def save(path: Path, net, mcfg, cfg, styles, it, seconds, history) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(
        {
            "model": {k: v.cpu() for k, v in net.state_dict().items()},
            "model_config": asdict(mcfg),
            "train_config": asdict(cfg),
            "styles": styles,
            "iter": it,
            "seconds": seconds,
            "history": history,
            "argv": sys.argv,
        },
        tmp,
    )
    tmp.replace(path)


if __name__ == "__main__":
    main(sys.argv[1:])
