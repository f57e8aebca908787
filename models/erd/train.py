"""Train Style-ERD on Bandai Namco dataset 2 (CPU-friendly, nanoGPT style: the config is the
dataclass below; override any field on the command line as --field=value).

    .venv/bin/python -m models.erd.train --minutes=50
    .venv/bin/python -m models.erd.train --resume --minutes=30           # continue run_dir/ckpt.pt
    .venv/bin/python -m models.erd.train --export=.data/erd/run/ckpt.pt   # write models/weights/erd
    sh models/erd/gpu_run.sh                                             # on a lent GPU (device)

A checkpoint (run_dir/ckpt.pt, every `ckpt_every` steps) holds the networks, optimisers, the
learning-rate schedule (a cosine over training time counted across sessions, or over steps with
`schedule_iters`), every random generator and the step, so `--resume` continues where it stopped.

Stages: (1) a content classifier with instance normalisation on real windows (for the
perceptual loss), (2) the generator + FT-Att discriminator: reconstruction (quaternion angle,
FK position, velocity) with target style = input style, LSGAN (real 1, fake -1, generator 0)
with R1 on real samples, perceptual loss against the input's classifier features. Neutral
clips get a random target style, styled clips the neutral target. Input labels are dropped at
random so that unlabelled streams work. Optional terms on the streamed rotations (what the
streaming model outputs: the decoder's bone directions with the input's twists, elbows and knees
as hinges fitted from the training rotations, `dataset.split_hinges`): `w_prior`
(the target style's range), `w_hinge` (hinge joints off their hinge), `w_adv_rot` (a second
discriminator); `w_teacher` anchors a fine-tune's transfer to the generator it started from.
"""

from __future__ import annotations

import json
import math
import random
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..runlog import start_run
from ..settings import REPO_ROOT
from ..train_config import parse_overrides, use_bf16


@dataclass
class TrainConfig:
    seed: int = 1234
    threads: int = 1  # the machine is shared; a GPU lease may take more
    device: str = "cpu"  # "cuda" on a GPU lease (`gpu_run.sh`); "auto" takes a GPU where there is one
    # bfloat16 autocast of the networks: "auto" where it is native (CUDA; a CPU with avx512_bf16 or
    # AMX), else "true" / "false". Measured on CPU in MODEL_CARD before it is left on there
    bf16: str = "false"
    resume: bool = False  # continue run_dir/ckpt.pt (its settings, then these overrides) if it exists
    data: str = ""  # a packed training set (`carry.py`) instead of the cache, e.g. on a GPU lease
    schedule_minutes: float = 0.0  # training time the cosine spans, across resumed sessions (0: `minutes`)
    schedule_iters: int = 0  # the cosine spans this many steps instead of time (reproducible runs)
    batch: int = 64
    window: int = 24
    minutes: float = 50.0  # wall-clock budget of the GAN stage
    max_iters: int = 200_000
    lr_g: float = 5e-4
    lr_d: float = 5e-4
    lr_decay_to: float = 0.2  # cosine to this fraction of lr over the time budget
    w_rot: float = 1.0
    w_pos: float = 0.5
    w_vel: float = 0.5
    w_adv: float = 1.0
    w_per: float = 0.1
    w_r1: float = 10.0
    # rotations: the streaming model outputs the decoder's pose with the input's twists and leaf
    # rotations (models.motion.twist); on transferred windows `w_prior` penalises a joint of that
    # pose leaving the target style's real range (angle to the style's mean beyond its p95)
    w_prior: float = 0.0
    # stage 4: twists and leaves from the input carried to the target style by this prior
    # (`rotation_prior.py`, e.g. models/weights/erd/leaf_prior.npz; empty = the input's), and a second
    # FT-Att discriminator over the streamed rotations (6-D per joint and their frame differences)
    leaf_prior: str = ""
    # hinge joints (fitted from the training rotations, `models.motion.hinge`): the streamed
    # rotations decode them as hinges (`hinge_decode`, as the runtime does); `w_hinge` penalises
    # what stays off the hinge (a straight limb, a parent twist at its real limit)
    hinge_decode: bool = True
    w_hinge: float = 0.0
    # fine-tuning: keep the transferred positions and velocities near those of the generator the
    # run started from (a frozen copy), so a rotation loss moves only what it must, not the style
    w_teacher: float = 0.0
    w_adv_rot: float = 0.0
    snapshot_every: int = 0  # also keep ckpt_<iter>.pt every so many iterations (0 = only the latest)
    d_warmup: int = 0  # iterations that train only the discriminator first (a new one, with --init_weights)
    p_drop_style: float = 0.3
    p_drop_content: float = 0.3
    p_neutral: float = 0.5
    clf_iters: int = 1500
    eval_every: int = 500
    render_every: int = 3000
    ckpt_every: int = 500
    latent: int = 32
    enc_hidden: int = 128
    dec_hidden: int = 128
    neutral_layers: int = 2
    style_layers: int = 2
    run_dir: str = str(REPO_ROOT / ".data" / "erd" / "run")
    out_dir: str = str(REPO_ROOT / "out" / "erd")
    export: str = ""  # path of a checkpoint to export to models/weights/erd instead of training
    init_from: str = ""  # continue from this checkpoint (generator, discriminator and its run's classifier)
    init_weights: str = ""  # start the generator from exported weights (e.g. models/weights/erd); new discriminator
    target_weights: str = ""  # e.g. "exhausted=3": neutral windows pick that target style 3x as often


def parse_args(argv: list[str]) -> TrainConfig:
    return parse_overrides(TrainConfig(), argv)


# --------------------------------------------------------------------------- pieces


def build(cfg: TrainConfig, stats: dict[str, np.ndarray]):
    from .features import POS, ROOTVEL, VEL
    from .model import ContentClassifier, ERDConfig, FTAttDiscriminator, Generator

    mcfg = ERDConfig(
        latent=cfg.latent,
        enc_hidden=cfg.enc_hidden,
        dec_hidden=cfg.dec_hidden,
        neutral_layers=cfg.neutral_layers,
        style_layers=cfg.style_layers,
    )
    std = torch.as_tensor(stats["std"])
    scale = {"pos": std[POS], "vel": torch.cat([std[VEL], std[ROOTVEL]])}
    gen = Generator(mcfg, stats["mean"], stats["std"])
    disc = FTAttDiscriminator(mcfg, 63 + 66, cfg.window - 1, scale)
    clf = ContentClassifier(mcfg, 84 + 63 + 66, scale)
    return mcfg, gen, disc, clf, scale


class RotationDiscriminator(torch.nn.Module):
    """The FT-Att discriminator over `rotation_view` (the generator's swings with the leaf
    prior's twists and leaves), so that a style's rotations, not only its positions, are judged."""

    def __init__(self, mcfg, frames: int):
        super().__init__()
        from .model import FTAttDiscriminator

        self.net = FTAttDiscriminator(mcfg, 21 * 12, frames, {})

    def forward(self, view: torch.Tensor, style: torch.Tensor, content: torch.Tensor) -> torch.Tensor:
        return self.net(view.transpose(1, 2), style, content)


class Losses:
    def __init__(self, skeleton, scale):
        from .model import fk_local

        self.offsets = torch.as_tensor(skeleton.offsets, dtype=torch.float32)
        self.parents = skeleton.parents
        self.fk_local = fk_local
        self.scale = scale

    def real_view(self, x):
        from .features import NB, POS, ROOTVEL, ROT
        from .model import window_motion

        B, T, _ = x.shape
        return window_motion(x[..., POS].reshape(B, T, NB, 3), x[..., ROOTVEL], x[..., ROT].reshape(B, T, NB, 4))

    def fake_view(self, out):
        from .model import window_motion

        pos = self.fk_local(out["rot"], out["height"], self.offsets, self.parents)
        return window_motion(pos, out["root_vel"], out["rot"])

    def recon(self, out, view, real, x):
        from .features import NB, ROT

        B, T, _ = x.shape
        q_real = x[..., ROT].reshape(B, T, NB, 4)
        dot = (out["rot"] * q_real).sum(-1)
        rot = (4 * (1 - dot.pow(2))).mean()  # 4 sin^2(angle/2) ~ angle^2, smooth at 0
        pos = ((view["pos"] - real["pos"]) / self.scale["pos"]).pow(2).mean()
        vel = ((view["vel"] - real["vel"]) / self.scale["vel"]).pow(2).mean()
        return rot, pos, vel


def style_rotation_prior(split) -> tuple[torch.Tensor, torch.Tensor]:
    """Per style (7) and body joint (21): the mean of the real training rotations (feature
    quaternions: Hips without its yaw, hemisphere-aligned) and the p95 angle to it (radians)."""
    from ..motion.rotations import quat_angle, quat_mean
    from .features import NB, ROT

    frame_style = np.repeat(split.style, split.lengths)
    means, p95s = [], []
    for s in range(int(split.style.max()) + 1):
        q = split.feats[frame_style == s][:, ROT].reshape(-1, NB, 4).astype(np.float64)
        q = q[:: max(1, len(q) // 60_000)]
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        mean = quat_mean(q, axis=0)
        means.append(mean)
        p95s.append(np.percentile(quat_angle(q, mean), 95, axis=0))
    return torch.as_tensor(np.stack(means), dtype=torch.float32), torch.as_tensor(np.stack(p95s), dtype=torch.float32)


def streamed_rotations(
    skeleton, rot: torch.Tensor, x: torch.Tensor, source: torch.Tensor | None = None, hinges=None
) -> torch.Tensor:
    """(B, T, 21, 4) the rotations the streaming model outputs for decoder rotations `rot`: its
    bone directions with the twists and leaf rotations of `source` (B, T, 21, 4; default the
    input's), and with `hinges` (`models.motion.hinge.Hinges`) its elbows and knees as hinges,
    as `ERDModel` does."""
    from ..motion.twist import transfer_twist_t

    root = torch.zeros(rot.shape[:2] + (1, 4), dtype=rot.dtype, device=rot.device)
    root[..., 3] = 1.0
    full = lambda q: torch.cat([root, q], dim=-2)  # noqa: E731  (joint_Root, static)
    src = real_rot(x) if source is None else source
    return transfer_twist_t(skeleton, full(src), full(rot), hinges)[..., 1:, :]


def leaf_source(prior, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B, T, 21, 4) the twist/leaf source the streaming model uses toward `target` (B,) (index
    in the 7 styles): the input's rotations carried by the leaf prior (`rotation_prior.py`)."""
    q = real_rot(x).double().numpy()
    B, T = q.shape[:2]
    full = np.zeros((B * T, 22, 4))
    full[..., 3] = 1.0
    full[:, 1:] = q.reshape(B * T, 21, 4)
    w = np.repeat(one_hot_targets(target).double().numpy(), T, axis=0)
    src = prior(full, w)[:, 1:]
    return torch.as_tensor(src.reshape(B, T, 21, 4), dtype=x.dtype)


def rotation_view(rot: torch.Tensor) -> torch.Tensor:
    """(B, T-1, 21*12) the rotation discriminator's view of rotations (B, T, 21, 4): 6-D per
    joint (as the eval suite's rotation judge reads them) and their frame-to-frame differences."""
    from ..motion.rotations_torch import quat_to_matrix_t

    m = quat_to_matrix_t(rot)
    six = torch.cat([m[..., :, 0], m[..., :, 1]], -1).flatten(2)
    return torch.cat([six[:, 1:], six[:, 1:] - six[:, :-1]], -1)


def prior_loss(rot: torch.Tensor, target: torch.Tensor, prior: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Mean squared angle (radians) by which rotations (B, T, 21, 4) lie beyond the target
    style's (B,) real p95 angle from its mean rotation, per joint."""
    mean, p95 = prior[0][target][:, None], prior[1][target][:, None]  # (B, 1, 21, 4), (B, 1, 21)
    cos = (rot * mean).sum(-1).abs() / rot.norm(dim=-1).clamp_min(1e-8)
    angle = 2 * torch.acos(cos.clamp(max=1 - 1e-6))
    return torch.relu(angle - p95).pow(2).mean()


def target_probs(spec: str) -> torch.Tensor:
    """Sampling probabilities of the 6 target styles for neutral windows; uniform unless `spec`
    ("style=factor,...") boosts styles that come out weak."""
    from .dataset import TARGET_STYLES

    w = torch.ones(len(TARGET_STYLES))
    for item in filter(None, spec.split(",")):
        name, _, factor = item.partition("=")
        if name not in TARGET_STYLES:
            raise SystemExit(f"unknown target style {name!r}; known: {', '.join(TARGET_STYLES)}")
        w[TARGET_STYLES.index(name)] = float(factor)
    return w / w.sum()


def one_hot_targets(style: torch.Tensor) -> torch.Tensor:
    """(B,) style index in the 7 styles -> (B, 6) branch weights (neutral = zeros)."""
    return F.one_hot(style.clamp_min(1) - 1, 6).float() * (style > 0).float()[:, None]


# --------------------------------------------------------------------------- stages


def train_classifier(cfg, clf, losses, train_s, val_s, log, device=torch.device("cpu")):
    opt = torch.optim.Adam(clf.parameters(), lr=1e-3)
    bar = tqdm(total=cfg.clf_iters, desc="classifier", mininterval=5, file=sys.stderr)
    for it in range(cfg.clf_iters):
        bar.update(1)
        b = to_device(train_s.sample(cfg.batch), device)
        logits, _ = clf(clf.prepare(losses.real_view(b["x"])))
        loss = F.cross_entropy(logits, b["content"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % 100 == 0:
            bar.set_postfix(loss=f"{loss.item():.3f}")
    clf.eval()
    with torch.no_grad():
        v = to_device(val_s.fixed(2), device)
        logits, _ = clf(clf.prepare(losses.real_view(v["x"])))
        acc = (logits.argmax(-1) == v["content"]).float().mean().item()
    log(f"content classifier: val window accuracy {acc:.3f}")
    for p in clf.parameters():
        p.requires_grad_(False)
    return acc


@torch.no_grad()
def validate(gen, disc, clf, losses, v, hinges=None, skeleton=None, decode=None) -> dict[str, float]:
    """Losses on fixed validation windows; with `hinges` and `skeleton`, how far the streamed
    transfer (decoded with `decode`, the hinges or None) leaves the hinges."""
    gen.eval()
    x, style, content = v["x"], v["style"], v["content"]
    real = losses.real_view(x)
    out_stats = {}
    for tag, s_in, c_in in (
        ("labels", style, content),
        ("nolabels", torch.full_like(style, -1), torch.full_like(content, -1)),
    ):
        out = gen(x, s_in, c_in, one_hot_targets(style))
        view = losses.fake_view(out)
        rot, pos, vel = losses.recon(out, view, real, x)
        dq = (out["rot"] * real_rot(x)).sum(-1).abs().clamp(max=1.0)
        out_stats[f"{tag}/rot_deg"] = torch.rad2deg(2 * torch.acos(dq)).mean().item()
        out_stats.update({f"{tag}/rot": rot.item(), f"{tag}/pos": pos.item(), f"{tag}/vel": vel.item()})
        # transfer: neutral windows -> every style; styled -> neutral
        neutral = style == 0
        target = torch.where(neutral, 1 + torch.arange(len(style), device=style.device) % 6, torch.zeros_like(style))
        fake = gen(x, s_in, c_in, one_hot_targets(target))
        fview = losses.fake_view(fake)
        logits, _ = clf(clf.prepare(fview))
        out_stats[f"{tag}/content_acc"] = (logits.argmax(-1) == content).float().mean().item()
        out_stats[f"{tag}/d_fake"] = disc(disc.prepare(fview), target, content).mean().item()
        dq = (fake["rot"] * real_rot(x)).sum(-1).abs().clamp(max=1.0)
        out_stats[f"{tag}/transfer_deg"] = torch.rad2deg(2 * torch.acos(dq)).mean().item()
        if hinges is not None and skeleton is not None:  # the streamed transfer's hinge joints off their hinge
            off = hinge_loss(streamed_rotations(skeleton, fake["rot"], x, hinges=decode), hinges, skeleton).sqrt()
            out_stats[f"{tag}/off_hinge_deg"] = math.degrees(math.asin(min(off.item(), 1.0)))
    out_stats["d_real"] = disc(disc.prepare(real), style, content).mean().item()
    gen.train()
    return out_stats


def real_rot(x):
    from .features import NB, ROT

    return x[..., ROT].reshape(x.shape[0], x.shape[1], NB, 4)


def render(gen, maker, out_dir: Path, tag: str, clips_motions) -> None:
    from ..motion.render import render_contact_sheet, render_gif
    from .dataset import TARGET_STYLES
    from .offline import stylise

    gen.eval()
    for name, motion in clips_motions:
        outs, titles = [motion], ["input"]
        for style in ("elderly", "exhausted"):
            w = np.zeros(6)
            w[TARGET_STYLES.index(style)] = 1.0
            outs.append(stylise(gen, maker, motion, w, style_in=0, content=-1))
            titles.append(style)
        render_contact_sheet(outs, out_dir / f"{tag}_{name}.png", frames=8, titles=titles)
        if tag == "final":
            render_gif(outs, out_dir / f"{tag}_{name}.gif", titles=titles)
    gen.train()


def hinge_loss(rot: torch.Tensor, hinges, skeleton) -> torch.Tensor:
    """Mean squared sine of the angle by which each hinge joint's bone (rotations (B, T, 21, 4),
    `hinges` a `models.motion.hinge.Hinges`) leaves the plane normal to its hinge axis: zero
    exactly when the joint turns as a hinge."""
    from ..motion.rotations_torch import quat_apply_t
    from ..motion.twist import bone_axes

    if len(hinges.joints) == 0:
        return rot.new_zeros(())
    as_t = lambda a: torch.as_tensor(a, dtype=rot.dtype, device=rot.device)  # noqa: E731
    q = rot[..., hinges.joints - 1, :]  # body indices: joint_Root is not in `rot`
    bone, hinge = as_t(bone_axes(skeleton)[hinges.joints]), as_t(hinges.axes)
    return (quat_apply_t(q, bone.expand(q.shape[:-1] + (3,))) * hinge).sum(-1).pow(2).mean()


@dataclass
class Schedule:
    """Cosine learning-rate factor (from 1 to `decay_to`) over `total` seconds of training counted
    across resumed sessions, or over `total` steps when `by_steps` (reproducible)."""

    decay_to: float
    total: float
    by_steps: bool = False
    elapsed_s: float = 0.0

    def progress(self, it: int) -> float:
        done = it if self.by_steps else self.elapsed_s
        return min(done / max(self.total, 1e-9), 1.0)

    def factor(self, it: int) -> float:
        return self.decay_to + (1 - self.decay_to) * 0.5 * (1 + math.cos(math.pi * self.progress(it)))


def rng_state(sampler_rng: np.random.Generator) -> dict:
    return {
        "sampler": sampler_rng.bit_generator.state,
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        "python": random.getstate(),
    }


def set_rng_state(sampler_rng: np.random.Generator, state: dict) -> None:
    sampler_rng.bit_generator.state = state["sampler"]
    torch.set_rng_state(state["torch"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    random.setstate(state["python"])


def to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def main(argv: list[str]) -> None:
    cfg = parse_args(argv)
    if cfg.export:
        from .runtime import export_weights

        print(export_weights(Path(cfg.export)))
        return
    resume = Path(cfg.run_dir) / "ckpt.pt" if cfg.resume else None
    ck = None
    if resume is not None and resume.exists():
        ck = torch.load(resume, map_location="cpu", weights_only=False)
        cfg = parse_overrides(TrainConfig(**ck["train_config"]), argv)  # the run's settings, then today's overrides
        cfg.resume = True
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto" else cfg.device)
    bf16 = use_bf16(cfg.bf16, device)
    from ..motion.assets import bandai_namco_skeleton
    from .dataset import WindowSampler, load_split, load_stats
    from .features import FeatureMaker

    run_dir, out_dir = Path(cfg.run_dir), Path(cfg.out_dir)
    log = start_run(run_dir, out_dir)

    t_start = time.time()
    if cfg.data:  # a packed training set (`carry.py`): no cache, no raw mocap
        from .carry import unpack

        splits, stats = unpack(Path(cfg.data))
        train_split, val_split = splits["train"], splits["val"]
    else:
        stats = load_stats()
        train_split, val_split = load_split("train"), load_split("val")
    train_s = WindowSampler(train_split, cfg.window, cfg.p_neutral, seed=cfg.seed)
    val_s = WindowSampler(val_split, cfg.window, cfg.p_neutral, seed=cfg.seed + 1)
    vfixed = to_device(val_s.fixed(2), device)
    skeleton = bandai_namco_skeleton()
    maker = FeatureMaker(skeleton, stats["ref"])
    render_motions = []
    if cfg.render_every and not cfg.data:
        from ..data import build_index, load_motions, select

        index = build_index(["bandai-namco-2"])
        render_clips = (
            select(index, split="val", style="normal", content=("walk",))[:1]
            + select(index, split="val", style="normal", content=("wave-right-hand",))[:1]
        )
        render_motions = [(c.name, m) for c, m in zip(render_clips, load_motions(render_clips))]
    mcfg, gen, disc, clf, scale = build(cfg, stats)
    scale = {k: v.to(device) for k, v in scale.items()}
    losses = Losses(skeleton, scale)
    losses.offsets = losses.offsets.to(device)
    n_g = sum(p.numel() for p in gen.parameters())
    n_d = sum(p.numel() for p in disc.parameters())
    log(f"config {json.dumps(asdict(cfg))}; device {device}, bfloat16 {bf16}; resumed from {resume if ck else None}")
    log(f"generator {n_g} params, discriminator {n_d}, classifier {sum(p.numel() for p in clf.parameters())}")

    if ck is not None:  # resume: every network, the classifier its run trained
        gen.load_state_dict(ck["generator"])
        disc.load_state_dict(ck["discriminator"])
        clf.load_state_dict(torch.load(run_dir / "classifier.pt", map_location="cpu"))
        clf_acc = ck["classifier_val_acc"]
    else:
        if cfg.init_weights:  # fine-tune the committed generator; discriminator and classifier anew
            from .runtime import load as load_exported

            gen.load_state_dict(load_exported(Path(cfg.init_weights)).torch_generator().state_dict())
            log(f"generator initialised from {cfg.init_weights}")
        if cfg.init_from:  # fine-tune: same networks, the classifier its run trained
            init = torch.load(cfg.init_from, map_location="cpu", weights_only=False)
            gen.load_state_dict(init["generator"])
            disc.load_state_dict(init["discriminator"])
            clf.load_state_dict(torch.load(Path(cfg.init_from).with_name("classifier.pt"), map_location="cpu"))
            clf_acc = init["classifier_val_acc"]
            log(f"initialised from {cfg.init_from} (iteration {init['iter']})")
    teacher = None
    if cfg.w_teacher:  # the generator as it starts (or as the resumed run started)
        import copy

        teacher = copy.deepcopy(gen)
        if ck is not None and ck.get("teacher") is not None:
            teacher.load_state_dict(ck["teacher"])
        teacher.eval().requires_grad_(False).to(device)
    gen.to(device)
    disc.to(device)
    clf.to(device)
    if ck is None and not cfg.init_from:
        clf_acc = train_classifier(cfg, clf, losses, train_s, val_s, log, device)
    clf.eval().requires_grad_(False)
    torch.save(clf.state_dict(), run_dir / "classifier.pt")
    p_target = target_probs(cfg.target_weights)
    prior_mean, prior_p95 = style_rotation_prior(train_s.s)
    prior = (prior_mean.to(device), prior_p95.to(device))
    from .dataset import split_hinges

    hinges = split_hinges(train_s.s, skeleton)
    decode = hinges if cfg.hinge_decode else None
    log(f"hinge joints {[skeleton.names[j] for j in hinges.joints]}, decoded as hinges: {cfg.hinge_decode}")
    leaf_prior = None
    if cfg.leaf_prior:
        from ..motion.style_carry import StyleCarry

        leaf_prior = StyleCarry.load(Path(cfg.leaf_prior))
        log(f"twists and leaves carried by {cfg.leaf_prior}")
    disc_rot = RotationDiscriminator(mcfg, cfg.window - 1).to(device) if cfg.w_adv_rot else None
    opt_dr = torch.optim.Adam(disc_rot.parameters(), lr=cfg.lr_d, betas=(0.5, 0.999)) if disc_rot else None
    opt_g = torch.optim.Adam(gen.parameters(), lr=cfg.lr_g, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.lr_d, betas=(0.5, 0.999))
    if cfg.schedule_iters:
        schedule = Schedule(cfg.lr_decay_to, float(cfg.schedule_iters), by_steps=True)
    else:
        schedule = Schedule(cfg.lr_decay_to, 60 * (cfg.schedule_minutes or cfg.minutes))
    history: list[dict] = []
    it = 0
    if ck is not None:
        opt_g.load_state_dict(ck["opt_g"])
        opt_d.load_state_dict(ck["opt_d"])
        if disc_rot is not None and opt_dr is not None and ck.get("disc_rot") is not None:
            disc_rot.load_state_dict(ck["disc_rot"])
            opt_dr.load_state_dict(ck["opt_dr"])
        total = schedule.total if (cfg.schedule_minutes or cfg.schedule_iters) else ck["schedule"]["total"]
        schedule = Schedule(**{**ck["schedule"], "total": total})
        set_rng_state(train_s.rng, ck["rng"])
        it, history = ck["iter"], ck["history"]
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)

    def checkpoint(path: Path) -> None:
        save(
            path,
            gen,
            disc,
            mcfg,
            cfg,
            stats,
            it,
            schedule.elapsed_s,
            history,
            clf_acc,
            train={
                "opt_g": opt_g.state_dict(),
                "opt_d": opt_d.state_dict(),
                "disc_rot": None if disc_rot is None else disc_rot.state_dict(),
                "opt_dr": None if opt_dr is None else opt_dr.state_dict(),
                "schedule": asdict(schedule),
                "rng": rng_state(train_s.rng),
                "teacher": None if teacher is None else {k: v.cpu() for k, v in teacher.state_dict().items()},
            },
        )

    t0, budget, first_it, seconds0 = time.time(), cfg.minutes * 60, it, schedule.elapsed_s
    bar = tqdm(total=cfg.max_iters, initial=it, desc="style-erd", mininterval=10, file=sys.stderr)
    last = time.time()
    while it < cfg.max_iters and time.time() - t0 < budget and schedule.progress(it) < 1.0:
        factor = schedule.factor(it)
        for opt, base in ((opt_g, cfg.lr_g), (opt_d, cfg.lr_d), (opt_dr, cfg.lr_d)):
            if opt is None:
                continue
            for group in opt.param_groups:
                group["lr"] = base * factor
        b = to_device(train_s.sample(cfg.batch), device)
        x, style, content = b["x"], b["style"], b["content"]
        B = len(x)
        target = torch.where(
            style == 0,
            1 + torch.multinomial(p_target, B, replacement=True).to(device),
            torch.zeros_like(style),
        )
        s_in = torch.where(torch.rand(B).to(device) < cfg.p_drop_style, torch.full_like(style, -1), style)
        c_in = torch.where(torch.rand(B).to(device) < cfg.p_drop_content, torch.full_like(content, -1), content)
        real = losses.real_view(x)

        # ---- generator (reconstruction and transfer in one batched pass)
        with autocast:
            outs = gen.forward_multi(x, s_in, c_in, [one_hot_targets(style), one_hot_targets(target)])
        out = {k: torch.cat([outs[0][k], outs[1][k]]).float() for k in outs[0]}
        view = losses.fake_view(out)
        rec = {k: v[:B] for k, v in out.items()}
        rec_view = {k: v[:B] for k, v in view.items()}
        fake_view = {k: v[B:] for k, v in view.items()}
        l_rot, l_pos, l_vel = losses.recon(rec, rec_view, real, x)
        with autocast:
            l_adv = disc(disc.prepare(fake_view), target, content).float().pow(2).mean()
            _, f_fake = clf(clf.prepare(fake_view))
            with torch.no_grad():
                _, f_real = clf(clf.prepare(real))
        l_per = torch.zeros((), device=device)
        for a, b_ in zip(f_fake, f_real):
            l_per = l_per + F.mse_loss(a.float(), b_.float())
        streamed = None
        if cfg.w_prior or cfg.w_hinge or disc_rot is not None:
            source = leaf_source(leaf_prior, x, target) if leaf_prior is not None else None
            streamed = streamed_rotations(skeleton, out["rot"][B:], x, source, decode)
        zero = torch.zeros((), device=device)
        l_teacher = zero
        if teacher is not None:
            with torch.no_grad(), autocast:
                t_out = teacher(x, s_in, c_in, one_hot_targets(target))
            t_view = losses.fake_view({k: v.float() for k, v in t_out.items()})
            l_teacher = sum(((fake_view[k] - t_view[k]) / scale[k]).pow(2).mean() for k in ("pos", "vel"))
        l_prior = prior_loss(streamed, target, prior) if cfg.w_prior and streamed is not None else zero
        l_hinge = hinge_loss(streamed, hinges, skeleton) if cfg.w_hinge and streamed is not None else zero
        l_adv_rot = (
            disc_rot(rotation_view(streamed), target, content).pow(2).mean()
            if disc_rot is not None and streamed is not None
            else zero
        )
        loss_g = (
            cfg.w_rot * l_rot
            + cfg.w_pos * l_pos
            + cfg.w_vel * l_vel
            + cfg.w_adv * l_adv
            + cfg.w_per * l_per
            + cfg.w_prior * l_prior
            + cfg.w_hinge * l_hinge
            + cfg.w_teacher * l_teacher
            + cfg.w_adv_rot * l_adv_rot
        )
        if it >= cfg.d_warmup:
            opt_g.zero_grad()
            loss_g.backward()
            opt_g.step()

        # ---- discriminator (LSGAN, R1 on real; the gradient penalty in float32)
        real_in = disc.prepare(real).detach().requires_grad_(True)
        d_real = disc(real_in, style, content)
        (grad,) = torch.autograd.grad(d_real.sum(), real_in, create_graph=True)
        r1 = grad.pow(2).sum((1, 2)).mean()
        with autocast:
            d_fake = disc(disc.prepare({k: v.detach() for k, v in fake_view.items()}), target, content).float()
        loss_d = (d_real - 1).pow(2).mean() + (d_fake + 1).pow(2).mean() + cfg.w_r1 * r1
        opt_d.zero_grad()
        loss_d.backward()
        opt_d.step()
        if disc_rot is not None and opt_dr is not None and streamed is not None:  # the same on real rotations
            rv = rotation_view(real_rot(x)).detach().requires_grad_(True)
            dr_real = disc_rot(rv, style, content)
            (grad,) = torch.autograd.grad(dr_real.sum(), rv, create_graph=True)
            dr_fake = disc_rot(rotation_view(streamed.detach()), target, content)
            loss_dr = (
                (dr_real - 1).pow(2).mean() + (dr_fake + 1).pow(2).mean() + cfg.w_r1 * grad.pow(2).sum((1, 2)).mean()
            )
            opt_dr.zero_grad()
            loss_dr.backward()
            opt_dr.step()

        it += 1
        now = time.time()
        schedule.elapsed_s += now - last
        last = now
        bar.update(1)
        if it % 50 == 0:
            bar.set_postfix(
                rot=f"{l_rot.item():.4f}",
                pos=f"{l_pos.item():.4f}",
                adv=f"{l_adv.item():.3f}",
                hinge=f"{l_hinge.item():.4f}",
                teacher=f"{float(l_teacher):.4f}",
                prior=f"{l_prior.item():.4f}",
                per=f"{l_per.item():.3f}",
                d=f"{loss_d.item():.3f}",
            )
        if it % cfg.eval_every == 0:
            v = validate(gen, disc, clf, losses, vfixed, hinges, skeleton, decode)
            v.update(
                iter=it,
                minutes=round(schedule.elapsed_s / 60, 2),
                it_per_s=round((it - first_it) / max(schedule.elapsed_s - seconds0, 1e-9), 2),
                lr_factor=round(factor, 4),
                train_rot=l_rot.item(),
                train_pos=l_pos.item(),
                train_adv=l_adv.item(),
                train_per=l_per.item(),
                train_d=loss_d.item(),
                train_prior=l_prior.item(),
                train_hinge=l_hinge.item(),
                train_teacher=float(l_teacher),
                train_adv_rot=l_adv_rot.item(),
            )
            history.append(v)
            log("val " + " ".join(f"{k}={val:.4g}" if isinstance(val, float) else f"{k}={val}" for k, val in v.items()))
            last = time.time()  # validation is not training time
        if it % cfg.ckpt_every == 0:
            checkpoint(run_dir / "ckpt.pt")
        if cfg.snapshot_every and it % cfg.snapshot_every == 0:
            save(run_dir / f"ckpt_{it:06d}.pt", gen, disc, mcfg, cfg, stats, it, schedule.elapsed_s, history, clf_acc)
        if render_motions and it % cfg.render_every == 0:
            render(gen, maker, out_dir, f"it{it:06d}", render_motions)
    bar.close()
    v = validate(gen, disc, clf, losses, vfixed, hinges, skeleton, decode)
    v.update(iter=it, minutes=round(schedule.elapsed_s / 60, 2))
    history.append(v)
    log("final val " + " ".join(f"{k}={val:.4g}" for k, val in v.items()))
    checkpoint(run_dir / "ckpt.pt")
    if render_motions:
        render(gen, maker, out_dir, "final", render_motions)
    trained = schedule.elapsed_s - seconds0
    log(
        f"done: {it} iterations ({(it - first_it) / max(trained, 1e-9):.2f} it/s this session), "
        f"{schedule.elapsed_s / 60:.1f} min of training in all, this session {(time.time() - t_start) / 60:.1f} min"
    )


def save(path, gen, disc, mcfg, cfg, stats, it, seconds, history, clf_acc, train: dict | None = None) -> None:
    """A checkpoint; with `train` (optimisers, schedule, RNG) one that `--resume` continues."""
    tmp = path.with_suffix(".tmp")
    torch.save(
        {
            "generator": {k: v.detach().cpu() for k, v in gen.state_dict().items()},
            "discriminator": {k: v.detach().cpu() for k, v in disc.state_dict().items()},
            "model_config": asdict(mcfg),
            "train_config": asdict(cfg),
            "ref": stats["ref"],
            "iter": it,
            "seconds": seconds,
            "history": history,
            "classifier_val_acc": clf_acc,
            "argv": sys.argv,
            **(train or {}),
        },
        tmp,
    )
    tmp.replace(path)


if __name__ == "__main__":
    main(sys.argv[1:])
