"""Train Style-ERD on Bandai Namco dataset 2, nanoGPT style: the config is the dataclass below,
any field overridable on the command line as --field=value.

    .venv/bin/python -m models.erd.train --minutes=50
    .venv/bin/python -m models.erd.train --resume --minutes=30           # continue run_dir/ckpt.pt
    .venv/bin/python -m models.erd.train --export=.data/erd/run/ckpt.pt   # write models/weights/erd
    sh models/erd/gpu_run.sh                                             # on a lent GPU (device)

A content classifier (perceptual loss), then the generator against an FT-Att discriminator
(LSGAN, R1), labels dropped at random so unlabelled streams work. `w_*` terms act on the streamed
rotations; `p_aug` shows windows as another performer's capture would (`augment_input`).
"""

from __future__ import annotations

import copy
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .. import training
from ..motion.rotations import quat_angle, quat_mean
from ..motion.rotations_torch import quat_apply_t, quat_mul_t
from ..motion.twist import bone_axes, transfer_twist_t
from ..settings import REPO_ROOT
from .dataset import TARGET_STYLES, split_hinges
from .features import NB, POS, ROOTVEL, ROT, VEL
from .model import ContentClassifier, ERDConfig, FTAttDiscriminator, Generator, fk_local, window_motion


@dataclass
class TrainConfig:
    seed: int = 1234
    threads: int = 1  # the machine is shared; a GPU lease may take more
    device: str = "cpu"  # "cuda" on a GPU lease (`gpu_run.sh`); "auto" takes a GPU where there is one
    bf16: str = "false"  # bfloat16 autocast: true, false, or "auto" where the hardware has it natively
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
    # terms on the streamed rotations: beyond the style's real p95 range, off the hinge
    w_prior: float = 0.0
    w_hinge: float = 0.0
    w_teacher: float = 0.0  # keep the transfer near the starting generator's, so only rotations move
    leaf_prior: str = ""  # twists and leaves carried to the target style (`rotation_prior.py`); "": see network_twists
    network_twists: bool = False  # the decoding takes twists and leaves from the decoder, not the input
    distill: str = ""  # the shipped pipeline's rotations of TRAIN neutral clips (`distill.py`)
    w_distill: float = 0.0  # transfers of neutral windows toward those rotations (the style in the core)
    hinge_decode: bool = True  # the streamed rotations decode hinge joints as hinges, as the runtime does
    # another performer's capture (`augment_input`): share of windows, joint offsets (degrees; arms more)
    p_aug: float = 0.0
    aug_deg: float = 12.0
    aug_deg_arms: float = 40.0
    aug_scale: float = 0.15  # root speed scaled by 1 +- up to this
    aug_noise_deg: float = 0.3  # per-frame rotation noise (std, degrees)
    aug_feat_noise: float = 0.05  # per-frame noise on position and velocity features (in feature std)
    w_smooth: float = 0.0  # streamed rotation acceleration beyond the input's and the style's (`smooth_loss`)
    teacher_vel: bool = True  # the teacher term also holds velocities (off: positions only)
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
    return training.parse_overrides(TrainConfig(), argv)


def build(cfg: TrainConfig, stats: dict[str, np.ndarray]):
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


class Losses:
    def __init__(self, skeleton, scale):
        self.offsets = torch.as_tensor(skeleton.offsets, dtype=torch.float32)
        self.parents = skeleton.parents
        self.scale = scale

    def real_view(self, x):
        B, T, _ = x.shape
        return window_motion(x[..., POS].reshape(B, T, NB, 3), x[..., ROOTVEL], x[..., ROT].reshape(B, T, NB, 4))

    def fake_view(self, out):
        pos = fk_local(out["rot"], out["height"], self.offsets, self.parents)
        return window_motion(pos, out["root_vel"], out["rot"])

    def recon(self, out, view, real, x):
        B, T, _ = x.shape
        q_real = x[..., ROT].reshape(B, T, NB, 4)
        dot = (out["rot"] * q_real).sum(-1)
        rot = (4 * (1 - dot.pow(2))).mean()  # 4 sin^2(angle/2) ~ angle^2, smooth at 0
        pos = ((view["pos"] - real["pos"]) / self.scale["pos"]).pow(2).mean()
        vel = ((view["vel"] - real["vel"]) / self.scale["vel"]).pow(2).mean()
        return rot, pos, vel


def style_rotation_prior(split) -> tuple[torch.Tensor, torch.Tensor]:
    """Per style (7) and body joint (21): real mean rotation and the p95 angle to it (radians)."""
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
    """(B, T, 21, 4) what the streaming model outputs for decoder rotations `rot` (`ERDModel`'s decoding)."""
    root = torch.zeros(rot.shape[:2] + (1, 4), dtype=rot.dtype, device=rot.device)
    root[..., 3] = 1.0
    full = lambda q: torch.cat([root, q], dim=-2)  # noqa: E731  (joint_Root, static)
    src = real_rot(x) if source is None else source
    return transfer_twist_t(skeleton, full(src), full(rot), hinges)[..., 1:, :]


def leaf_source(prior, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B, T, 21, 4) the input's rotations carried by the leaf prior toward `target` (B,)."""
    q = real_rot(x).double().numpy()
    B, T = q.shape[:2]
    full = np.zeros((B * T, 22, 4))
    full[..., 3] = 1.0
    full[:, 1:] = q.reshape(B * T, 21, 4)
    w = np.repeat(one_hot_targets(target).double().numpy(), T, axis=0)
    src = prior(full, w)[:, 1:]
    return torch.as_tensor(src.reshape(B, T, 21, 4), dtype=x.dtype)


def prior_loss(rot: torch.Tensor, target: torch.Tensor, prior: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Mean squared angle (radians) by which rotations lie beyond the target style's real p95."""
    mean, p95 = prior[0][target][:, None], prior[1][target][:, None]  # (B, 1, 21, 4), (B, 1, 21)
    cos = (rot * mean).sum(-1).abs() / rot.norm(dim=-1).clamp_min(1e-8)
    angle = 2 * torch.acos(cos.clamp(max=1 - 1e-6))
    return torch.relu(angle - p95).pow(2).mean()


def rotation_accel_t(q: torch.Tensor) -> torch.Tensor:
    """(B, T - 2, J) the eval's rotation acceleration (radians) of (B, T, J, 4), differentiable."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    conj = torch.cat([-q[..., :3], q[..., 3:]], -1)
    d = quat_mul_t(conj[:, :-1], q[:, 1:])
    turn = 2 * d[..., :3] * torch.where(d[..., 3:] < 0, -1.0, 1.0)
    return (turn[:, 1:] - turn[:, :-1]).pow(2).sum(-1).add(1e-12).sqrt()


def style_accel_p99(split) -> torch.Tensor:
    """(7, 21) per style and body joint, the p99 rotation acceleration of real training clips."""
    q = torch.as_tensor(split.feats[:, ROT].reshape(-1, NB, 4))
    out = torch.zeros(int(split.style.max()) + 1, NB)
    for s in range(len(out)):
        acc = [
            rotation_accel_t(q[a : a + n][None])[0]
            for a, n, st in zip(split.starts, split.lengths, split.style)
            if st == s and n > 2
        ]
        out[s] = torch.quantile(torch.cat(acc)[::3], 0.99, dim=0)
    return out


def smooth_loss(out: torch.Tensor, inp: torch.Tensor, target: torch.Tensor, p99: torch.Tensor) -> torch.Tensor:
    """Mean squared acceleration beyond the input's and the style's p99: only added jitter costs."""
    ref = torch.maximum(rotation_accel_t(inp).amax(1, keepdim=True), p99[target][:, None])
    return torch.rad2deg(torch.relu(rotation_accel_t(out) - ref)).pow(2).mean()


def random_turns(max_deg: torch.Tensor) -> torch.Tensor:
    """(..., 4) rotations about uniformly random axes by angles uniform in [0, max_deg] (...)."""
    axis = torch.randn(max_deg.shape + (3,), device=max_deg.device)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    half = torch.deg2rad(max_deg * torch.rand_like(max_deg)) / 2
    return torch.cat([axis * half.sin()[..., None], half.cos()[..., None]], -1)


def augment_input(
    x: torch.Tensor, cfg: TrainConfig, offsets: torch.Tensor, parents, names, std: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Windows x (B, T, 216) as another performer or recording might give them: (network input,
    reconstruction target). A share `cfg.p_aug` of windows get constant per-joint turns (more on
    clavicles and upper arms, where rigs differ most), per-frame shake and a root speed scale, the
    positions and velocities re-derived by FK; the input alone also gets feature noise."""
    B, T, _ = x.shape
    dev = x.device
    pick = torch.rand(B, device=dev) < cfg.p_aug
    if not pick.any():
        return x, x
    xs = x[pick]
    b = len(xs)
    arms = torch.tensor([("Shoulder" in n or "UpperArm" in n) for n in names[1:]], device=dev)
    max_deg = torch.where(arms, float(cfg.aug_deg_arms), float(cfg.aug_deg)).expand(b, 1, NB)
    turn = random_turns(max_deg.contiguous())
    noise = torch.randn(b, T, NB, 3, device=dev) * math.radians(cfg.aug_noise_deg) / 2
    shake = torch.cat([noise, torch.ones(b, T, NB, 1, device=dev)], -1)
    q = real_rot(xs)
    q2 = quat_mul_t(quat_mul_t(q, turn.expand(b, T, NB, 4)), shake)
    q2 = q2 / q2.norm(dim=-1, keepdim=True)
    q2 = torch.where((q2 * q).sum(-1, keepdim=True) < 0, -q2, q2)  # the features' hemisphere
    height = xs[..., POS][..., 1]
    delta = fk_local(q2, height, offsets, parents) - fk_local(q, height, offsets, parents)  # (b, T, 21, 3)
    dvel = torch.cat([delta[:, 1:2] - delta[:, :1], delta[:, 1:] - delta[:, :-1]], 1) * 30.0
    speed = cfg.aug_scale * (2 * torch.rand(b, 1, 1, device=dev) - 1)
    root = xs[..., ROOTVEL]
    tgt = xs.clone()
    tgt[..., ROT] = q2.flatten(2)
    tgt[..., POS] = xs[..., POS] + delta.flatten(2)
    tgt[..., VEL] = xs[..., VEL] + dvel.flatten(2) + (speed * root).repeat(1, 1, NB)
    tgt[..., ROOTVEL] = root * (1 + speed)
    inp = tgt.clone()
    for part in (POS, VEL):
        inp[..., part] = inp[..., part] + cfg.aug_feat_noise * std[part] * torch.randn_like(inp[..., part])
    x_in, x_tgt = x.clone(), x.clone()
    x_in[pick], x_tgt[pick] = inp, tgt
    return x_in, x_tgt


def distill_loss(rot: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """Mean 4 sin^2(angle / 2) (~ squared angle) to the teacher's rotations, either hemisphere."""
    dot = (rot * teacher.float()).sum(-1) / rot.norm(dim=-1).clamp_min(1e-8)
    return (4 * (1 - dot.pow(2))).mean()


def target_probs(spec: str) -> torch.Tensor:
    """Sampling probabilities of the 6 target styles; `spec` ("style=factor,...") boosts some."""
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


def train_classifier(cfg, clf, losses, train_s, val: dict[str, torch.Tensor], log, device: torch.device) -> float:
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
        logits, _ = clf(clf.prepare(losses.real_view(val["x"])))
        acc = (logits.argmax(-1) == val["content"]).float().mean().item()
    log(f"content classifier: val window accuracy {acc:.3f}")
    for p in clf.parameters():
        p.requires_grad_(False)
    return acc


@torch.no_grad()
def validate(gen, disc, clf, losses, v, hinges=None, skeleton=None, decode=None) -> dict[str, float]:
    """Losses on fixed validation windows; with `hinges` and `skeleton`, the hinge error too."""
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
    """Mean squared sine of each hinge joint's bone angle off the plane normal to its hinge axis."""
    if len(hinges.joints) == 0:
        return rot.new_zeros(())
    as_t = lambda a: torch.as_tensor(a, dtype=rot.dtype, device=rot.device)  # noqa: E731
    q = rot[..., hinges.joints - 1, :]  # body indices: joint_Root is not in `rot`
    bone, hinge = as_t(bone_axes(skeleton)[hinges.joints]), as_t(hinges.axes)
    return (quat_apply_t(q, bone.expand(q.shape[:-1] + (3,))) * hinge).sum(-1).pow(2).mean()


def to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


WEIGHTED = ("rot", "pos", "vel", "adv", "per", "prior", "hinge", "teacher", "distill", "smooth")  # cfg.w_<term>


def load_config(argv: list[str]) -> tuple[TrainConfig, dict | None]:
    return training.resume_config(TrainConfig(), argv)


@dataclass
class Data:
    """Training and validation windows, the skeleton and the clips rendered along the way."""

    stats: dict[str, np.ndarray]
    train: Any  # dataset.WindowSampler
    val: dict[str, torch.Tensor]  # fixed validation windows
    skeleton: Any
    maker: Any  # features.FeatureMaker
    render_motions: list

    @staticmethod
    def load(cfg: TrainConfig, device: torch.device) -> Data:
        from ..motion.assets import bandai_namco_skeleton
        from .dataset import WindowSampler, load_split, load_stats
        from .features import FeatureMaker

        if cfg.data:  # a packed training set (`carry.py`): no cache, no raw mocap
            from .carry import unpack

            splits, stats = unpack(Path(cfg.data))
            train_split, val_split = splits["train"], splits["val"]
        else:
            stats = load_stats()
            train_split, val_split = load_split("train"), load_split("val")
        train = WindowSampler(train_split, cfg.window, cfg.p_neutral, seed=cfg.seed)
        val = WindowSampler(val_split, cfg.window, cfg.p_neutral, seed=cfg.seed + 1)
        skeleton = bandai_namco_skeleton()
        motions = []
        if cfg.render_every and not cfg.data:
            from ..data import build_index, load_motions, select

            index = build_index(["bandai-namco-2"])
            pick = [select(index, split="val", style="normal", content=(c,))[:1] for c in ("walk", "wave-right-hand")]
            clips = pick[0] + pick[1]
            motions = [(c.name, m) for c, m in zip(clips, load_motions(clips))]
        vfixed = to_device(val.fixed(2), device)
        return Data(stats, train, vfixed, skeleton, FeatureMaker(skeleton, stats["ref"]), motions)


class Run:
    """The networks, optimisers and training state of a run: what a checkpoint holds."""

    def __init__(self, cfg: TrainConfig, ck: dict | None, data: Data, device: torch.device, log) -> None:
        """Networks built in a fixed order (runs repeat), restored from `ck` or initialised per `cfg`."""
        self.cfg, self.data, self.device, self.it = cfg, data, device, 0
        self.autocast = training.autocast(device, training.use_bf16(cfg.bf16, device))
        self.history: list[dict] = []
        self.mcfg, gen, disc, clf, scale = build(cfg, data.stats)
        self.gen, self.disc, self.clf = gen, disc, clf
        self.losses = Losses(data.skeleton, {k: v.to(device) for k, v in scale.items()})
        self.losses.offsets = self.losses.offsets.to(device)
        n_g, n_d = (sum(p.numel() for p in net.parameters()) for net in (gen, disc))
        log(f"generator {n_g} params, discriminator {n_d}, classifier {sum(p.numel() for p in clf.parameters())}")
        self.clf_acc = None
        if ck is not None:  # resume: every network, the classifier its run trained
            gen.load_state_dict(ck["generator"])
            disc.load_state_dict(ck["discriminator"])
            clf.load_state_dict(torch.load(Path(cfg.run_dir) / "classifier.pt", map_location="cpu"))
            self.clf_acc = ck["classifier_val_acc"]
        elif cfg.init_weights:  # fine-tune the committed generator; discriminator and classifier anew
            from .runtime import load as load_exported

            gen.load_state_dict(load_exported(Path(cfg.init_weights)).torch_generator().state_dict())
            log(f"generator initialised from {cfg.init_weights}")
        if ck is None and cfg.init_from:  # fine-tune: same networks, the classifier its run trained
            init = torch.load(cfg.init_from, map_location="cpu", weights_only=False)
            gen.load_state_dict(init["generator"])
            disc.load_state_dict(init["discriminator"])
            clf.load_state_dict(torch.load(Path(cfg.init_from).with_name("classifier.pt"), map_location="cpu"))
            self.clf_acc = init["classifier_val_acc"]
            log(f"initialised from {cfg.init_from} (iteration {init['iter']})")
        self.teacher = None
        if cfg.w_teacher:  # the generator as it starts (or as the resumed run started)
            self.teacher = copy.deepcopy(gen)
            if ck is not None and ck.get("teacher") is not None:
                self.teacher.load_state_dict(ck["teacher"])
            self.teacher.eval().requires_grad_(False).to(device)
        gen.to(device)
        disc.to(device)
        clf.to(device)
        if self.clf_acc is None:
            self.clf_acc = train_classifier(cfg, clf, self.losses, data.train, data.val, log, device)
        clf.eval().requires_grad_(False)
        torch.save(clf.state_dict(), Path(cfg.run_dir) / "classifier.pt")
        self.p_target = target_probs(cfg.target_weights)
        mean, p95 = style_rotation_prior(data.train.s)
        self.prior = (mean.to(device), p95.to(device))
        self.accel_p99 = style_accel_p99(data.train.s).to(device) if cfg.w_smooth else None
        self.hinges = split_hinges(data.train.s, data.skeleton)
        self.decode = self.hinges if cfg.hinge_decode else None  # as the runtime decodes them
        log(f"hinge joints {[data.skeleton.names[j] for j in self.hinges.joints]}, decoded: {cfg.hinge_decode}")
        self.leaf_prior = None
        if cfg.leaf_prior:
            from ..motion.style_carry import StyleCarry

            self.leaf_prior = StyleCarry.load(Path(cfg.leaf_prior))
            log(f"twists and leaves carried by {cfg.leaf_prior}")
        self.distill = None
        if cfg.distill:  # frame row of the TRAIN cache -> its targets' row (-1: none)
            with np.load(cfg.distill) as z:
                self.distill = torch.as_tensor(z["targets"]).to(device)
                self.distill_row = torch.full((len(data.train.s.feats),), -1, dtype=torch.long)
                self.distill_row[torch.as_tensor(z["frames"])] = torch.arange(len(z["frames"]))
            self.distill_row = self.distill_row.to(device)
            log(f"distilling toward {cfg.distill} ({len(self.distill)} frames)")
        self.opt_g = torch.optim.Adam(gen.parameters(), lr=cfg.lr_g, betas=(0.5, 0.999))
        self.opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.lr_d, betas=(0.5, 0.999))
        if cfg.schedule_iters:
            self.schedule = training.Schedule(cfg.lr_decay_to, float(cfg.schedule_iters), by_steps=True)
        else:
            self.schedule = training.Schedule(cfg.lr_decay_to, 60 * (cfg.schedule_minutes or cfg.minutes))
        if ck is not None:
            self.restore(ck, data)
        self.optimizers = [(self.opt_g, cfg.lr_g), (self.opt_d, cfg.lr_d)]

    def restore(self, ck: dict, data: Data) -> None:
        """Optimisers, schedule, random generators and step of a resumed run."""
        self.opt_g.load_state_dict(ck["opt_g"])
        self.opt_d.load_state_dict(ck["opt_d"])
        cfg = self.cfg
        total = self.schedule.total if (cfg.schedule_minutes or cfg.schedule_iters) else None
        self.schedule = training.Schedule.resumed(ck["schedule"], total)
        training.set_rng_state(data.train.rng, ck["rng"])
        self.it, self.history = ck["iter"], ck["history"]

    def step(self) -> dict[str, float]:
        batch = to_device(self.data.train.sample(self.cfg.batch), self.device)
        return train_step(self.cfg, self, self.data, batch, self.it, self.autocast)

    def validate(self) -> dict[str, float]:
        data = self.data
        return validate(self.gen, self.disc, self.clf, self.losses, data.val, self.hinges, data.skeleton, self.decode)

    def report(self, terms: dict[str, float], factor: float, steps_per_s: float) -> dict:
        return dict(
            it_per_s=round(steps_per_s, 2), lr_factor=round(factor, 4), **{f"train_{k}": v for k, v in terms.items()}
        )

    def postfix(self, terms: dict[str, float]) -> dict[str, str]:
        return {k: f"{v:.4f}" for k, v in terms.items()}

    def checkpoint(self, path: Path, resumable: bool = True) -> None:
        """A checkpoint; a resumable one also holds what `--resume` needs (optimisers, RNG)."""
        data, it = self.data, self.it
        state = {
            "generator": {k: v.detach().cpu() for k, v in self.gen.state_dict().items()},
            "discriminator": {k: v.detach().cpu() for k, v in self.disc.state_dict().items()},
            "model_config": asdict(self.mcfg),
            "train_config": asdict(self.cfg),
            "ref": data.stats["ref"],
            "iter": it,
            "seconds": self.schedule.elapsed_s,
            "history": self.history,
            "classifier_val_acc": self.clf_acc,
            "argv": sys.argv,
        }
        if resumable:
            state.update(
                opt_g=self.opt_g.state_dict(),
                opt_d=self.opt_d.state_dict(),
                schedule=asdict(self.schedule),
                rng=training.rng_state(data.train.rng),
                teacher=None if self.teacher is None else {k: v.cpu() for k, v in self.teacher.state_dict().items()},
            )
        training.save_checkpoint(state, path)


def train_step(cfg: TrainConfig, run: Run, data: Data, b: dict[str, torch.Tensor], it: int, autocast) -> dict:
    """One generator and discriminator update on batch `b`; returns the loss terms."""
    gen, disc, clf, losses, device = run.gen, run.disc, run.clf, run.losses, b["x"].device
    x, style, content = b["x"], b["style"], b["content"]
    B = len(x)
    x_in = x
    if cfg.p_aug:  # another performer's or recording's window: read, reconstructed, and real to the discriminator
        x_in, x = augment_input(x, cfg, losses.offsets, losses.parents, data.skeleton.names, run.gen.std)
    # neutral windows go to a random style, styled ones to neutral; input labels dropped at random
    target = torch.where(
        style == 0, 1 + torch.multinomial(run.p_target, B, replacement=True).to(device), torch.zeros_like(style)
    )
    s_in = torch.where(torch.rand(B).to(device) < cfg.p_drop_style, torch.full_like(style, -1), style)
    c_in = torch.where(torch.rand(B).to(device) < cfg.p_drop_content, torch.full_like(content, -1), content)
    real = losses.real_view(x)

    # generator: reconstruction (target = input style) and transfer in one batched pass
    with autocast:
        outs = gen.forward_multi(x_in, s_in, c_in, [one_hot_targets(style), one_hot_targets(target)])
    out = {k: torch.cat([outs[0][k], outs[1][k]]).float() for k in outs[0]}
    view = losses.fake_view(out)
    fake_view = {k: v[B:] for k, v in view.items()}
    t: dict[str, torch.Tensor] = {}
    t["rot"], t["pos"], t["vel"] = losses.recon(
        {k: v[:B] for k, v in out.items()}, {k: v[:B] for k, v in view.items()}, real, x
    )
    with autocast:
        t["adv"] = disc(disc.prepare(fake_view), target, content).float().pow(2).mean()
        _, f_fake = clf(clf.prepare(fake_view))
        with torch.no_grad():
            _, f_real = clf(clf.prepare(real))
    t["per"] = torch.zeros((), device=device)
    for a, b_ in zip(f_fake, f_real):
        t["per"] = t["per"] + F.mse_loss(a.float(), b_.float())
    streamed = None
    if cfg.w_prior or cfg.w_hinge or cfg.w_smooth:
        source = leaf_source(run.leaf_prior, x, target) if run.leaf_prior is not None else None
        if source is None and cfg.network_twists:
            source = out["rot"][B:]
        streamed = streamed_rotations(data.skeleton, out["rot"][B:], x, source, run.decode)
    zero = torch.zeros((), device=device)
    t["teacher"] = zero
    if run.teacher is not None:  # keep the transfer near the generator the run started from
        with torch.no_grad(), autocast:
            t_out = run.teacher(x_in, s_in, c_in, one_hot_targets(target))
        t_view = losses.fake_view({k: v.float() for k, v in t_out.items()})
        keys = ("pos", "vel") if cfg.teacher_vel else ("pos",)
        t["teacher"] = sum(((fake_view[k] - t_view[k]) / losses.scale[k]).pow(2).mean() for k in keys)
    t["distill"] = zero
    if run.distill is not None:  # neutral windows whose every frame has a target
        rows = run.distill_row[b["idx"]]
        use = (target > 0) & (rows >= 0).all(1)
        if use.any():
            t["distill"] = distill_loss(out["rot"][B:][use], run.distill[rows[use], (target[use] - 1)[:, None]])
    t["prior"] = prior_loss(streamed, target, run.prior) if cfg.w_prior and streamed is not None else zero
    t["hinge"] = hinge_loss(streamed, run.hinges, data.skeleton) if cfg.w_hinge and streamed is not None else zero
    t["smooth"] = zero
    if cfg.w_smooth and streamed is not None and run.accel_p99 is not None:
        t["smooth"] = smooth_loss(streamed, real_rot(x), target, run.accel_p99)
    loss_g = sum(getattr(cfg, f"w_{k}") * t[k] for k in WEIGHTED)
    if it >= cfg.d_warmup:
        run.opt_g.zero_grad()
        loss_g.backward()
        run.opt_g.step()

    # discriminator: LSGAN with R1 on real windows (the gradient penalty in float32)
    real_in = disc.prepare(real).detach().requires_grad_(True)
    d_real = disc(real_in, style, content)
    (grad,) = torch.autograd.grad(d_real.sum(), real_in, create_graph=True)
    r1 = grad.pow(2).sum((1, 2)).mean()
    with autocast:
        d_fake = disc(disc.prepare({k: v.detach() for k, v in fake_view.items()}), target, content).float()
    t["d"] = (d_real - 1).pow(2).mean() + (d_fake + 1).pow(2).mean() + cfg.w_r1 * r1
    run.opt_d.zero_grad()
    t["d"].backward()
    run.opt_d.step()
    return {k: float(v.detach()) for k, v in t.items()}


def main(argv: list[str]) -> None:
    cfg, ck = load_config(argv)
    if cfg.export:
        from .runtime import export_weights

        print(export_weights(Path(cfg.export)))
        return
    device = training.seeded_device(cfg.threads, cfg.seed, cfg.device)
    bf16 = training.use_bf16(cfg.bf16, device)
    run_dir, out_dir = Path(cfg.run_dir), Path(cfg.out_dir)
    log = training.start_run(run_dir, out_dir)
    t_start = time.time()
    data = Data.load(cfg, device)
    run = Run(cfg, ck, data, device, log)
    log(f"config {json.dumps(asdict(cfg))}; device {device}, bfloat16 {bf16}; resumed: {ck is not None}")

    def render_at(it: int) -> None:
        render(run.gen, data.maker, out_dir, f"it{it:06d}", data.render_motions)

    every = [(cfg.render_every, render_at)] if data.render_motions else []
    steps_per_s = training.train(run, cfg, run.optimizers, log, "style-erd", every)
    if data.render_motions:
        render(run.gen, data.maker, out_dir, "final", data.render_motions)
    log(
        f"done: {run.it} iterations ({steps_per_s:.2f} it/s this session), "
        f"{run.schedule.elapsed_s / 60:.1f} min of training in all, this session {(time.time() - t_start) / 60:.1f} min"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
