"""Streaming Style-ERD: the project's `StreamingModel` interface in plain numpy (float64).

Weights live in `models/weights/erd/erd.npz` (generator parameters, normalisation, per-joint
reference rotations, the Bandai Namco skeleton) + `config.json`; `export_weights` writes them
from a training checkpoint.

State per session (every entry has the session axis first):
    h_neutral, c_neutral       (B, neutral_layers, H)   the neutral LSTM branch
    h_<style>, c_<style>       (B, style_layers, H)     one residual branch per target style
    prev_pos (B, 22, 3), prev_yaw (B,)                  previous input frame (causal velocities)
    out_root (B, 3)                                     last output Hips translation
    frame (B,)                                          frames seen
    style_in (B,), content (B,)                         input labels, -1 = unknown (the default)
Every residual branch advances every frame (whatever its weight), so switching or mixing styles
never meets a stale state; the output uses latent = neutral + sum_s w_s * branch_s.

Output root: the predicted facing-frame root velocity is integrated from the input's first root
position, turned by the input's facing yaw (the path keeps the input's shape and direction; the
speed follows the style); the height is predicted.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..interface import FrameBatch, State
from ..motion.skeleton import Skeleton
from .dataset import CONTENTS, STYLES, TARGET_STYLES
from models.motion.rotations import quat_mul

from .features import BODY, FPS, NB, POS, ROOTVEL, ROT, FeatureMaker, rotate_y, yaw_quat

WEIGHTS_FILE = "erd.npz"


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


class ERDModel:
    name = "erd"
    fps = FPS  # the model runs at 30 fps (Bandai Namco)

    def __init__(self, params: dict[str, np.ndarray], config: dict, skeleton: Skeleton,
                 mean: np.ndarray, std: np.ndarray, ref: np.ndarray, meta: dict | None = None):
        self.p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
        self.config = config
        self.meta = meta or {}
        self.skeleton = skeleton
        self.mean, self.std = np.asarray(mean, np.float64), np.asarray(std, np.float64)
        self.ref = np.asarray(ref, np.float64)
        self.maker = FeatureMaker(skeleton, self.ref)
        self.H = config["latent"]
        self.Ln, self.Ls = config["neutral_layers"], config["style_layers"]
        p = self.p
        self.enc = [(p[f"encoder.{i}.weight"].T.copy(), p[f"encoder.{i}.bias"]) for i in (0, 2, 4)]
        self.dec = [(p[f"decoder.{i}.weight"].T.copy(), p[f"decoder.{i}.bias"]) for i in (0, 2, 4)]
        self.neutral = [(p[f"neutral.weight_ih_l{l}"].T.copy(), p[f"neutral.weight_hh_l{l}"].T.copy(),
                         p[f"neutral.bias_ih_l{l}"] + p[f"neutral.bias_hh_l{l}"]) for l in range(self.Ln)]
        K = len(TARGET_STYLES)
        # style branches stacked: (K, in, 4H), (K, H, 4H), (K, 4H)
        self.branch = [(np.stack([p[f"branches.{k}.weight_ih_l{l}"].T for k in range(K)]),
                        np.stack([p[f"branches.{k}.weight_hh_l{l}"].T for k in range(K)]),
                        np.stack([p[f"branches.{k}.bias_ih_l{l}"] + p[f"branches.{k}.bias_hh_l{l}"] for k in range(K)]))
                       for l in range(self.Ls)]
        # the first layer's input is shared: one (in, K*4H) product
        w0 = self.branch[0][0]
        self.branch0_in = np.concatenate(list(w0), axis=1)

    # ------------------------------------------------------------------ interface

    def styles(self) -> list[str]:
        return list(TARGET_STYLES)

    def contents(self) -> list[str]:
        return list(CONTENTS)

    def init_state(self, batch: int, content: str | None = None, input_style: str | None = None) -> State:
        """Fresh sessions; `content`/`input_style` label the input stream when known (default: unknown)."""
        ci = CONTENTS.index(content) if content is not None else -1
        si = STYLES.index(input_style) if input_style is not None else -1
        row = ci if ci >= 0 else len(CONTENTS)
        state: State = {
            "h_neutral": np.repeat(self.p["neutral_h0"][row][None], batch, 0),
            "c_neutral": np.repeat(self.p["neutral_c0"][row][None], batch, 0),
        }
        for k, style in enumerate(TARGET_STYLES):
            state[f"h_{style}"] = np.repeat(self.p["style_h0"][k][None], batch, 0)
            state[f"c_{style}"] = np.repeat(self.p["style_c0"][k][None], batch, 0)
        state.update(prev_pos=np.zeros((batch, 22, 3)), prev_yaw=np.zeros(batch), out_root=np.zeros((batch, 3)),
                     frame=np.zeros(batch, dtype=np.int64), style_in=np.full(batch, si, dtype=np.int64),
                     content=np.full(batch, ci, dtype=np.int64))
        return state

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        root = np.asarray(frames.root, np.float64)
        rot_in = np.asarray(frames.rotations, np.float64)
        w = np.asarray(style_weights, np.float64)
        B = root.shape[0]
        if w.shape != (B, len(TARGET_STYLES)):
            raise ValueError(f"style_weights must be ({B}, {len(TARGET_STYLES)}), got {w.shape}")
        has_prev = state["frame"] > 0
        pos = self.maker.positions(root, rot_in)
        x, yaw = self.maker.features(rot_in, pos, state["prev_pos"], state["prev_yaw"], has_prev)
        new: State = {}
        y, new = self._network(x, state, w, new)
        rot = x[:, ROT].reshape(B, NB, 4) + y[:, :4 * NB].reshape(B, NB, 4)
        rot = rot / np.maximum(np.linalg.norm(rot, axis=-1, keepdims=True), 1e-6)
        root_vel = x[:, ROOTVEL] + y[:, 4 * NB:4 * NB + 3]
        height = x[:, POS][:, 1] + y[:, -1]
        step = rotate_y(root_vel, yaw) / FPS
        out_root = np.where(has_prev[:, None], state["out_root"] + step, root)
        out_root[:, 1] = height
        out_rot = rot_in.copy()
        out_rot[:, BODY] = rot
        out_rot[:, 1] = quat_mul(yaw_quat(yaw), rot[:, 0])
        new.update(prev_pos=pos, prev_yaw=yaw, out_root=out_root, frame=state["frame"] + 1,
                   style_in=state["style_in"].copy(), content=state["content"].copy())
        return FrameBatch(out_root, out_rot), new

    # ------------------------------------------------------------------ network

    def _network(self, x: np.ndarray, state: State, w: np.ndarray, new: State) -> tuple[np.ndarray, State]:
        B = x.shape[0]
        s1 = np.zeros((B, len(STYLES)))
        c1 = np.zeros((B, len(CONTENTS)))
        si, ci = state["style_in"], state["content"]
        s1[np.arange(B)[si >= 0], si[si >= 0]] = 1.0
        c1[np.arange(B)[ci >= 0], ci[ci >= 0]] = 1.0
        h = np.concatenate([(x - self.mean) / self.std, s1, c1], -1)
        for i, (W, b) in enumerate(self.enc):
            h = h @ W + b
            if i < 2:
                h = np.maximum(h, 0.0)
        z = h
        H = self.H
        # neutral branch
        hn, cn = state["h_neutral"].copy(), state["c_neutral"].copy()
        inp = z
        for l, (Wi, Wh, b) in enumerate(self.neutral):
            g = inp @ Wi + hn[:, l] @ Wh + b
            c = _sigmoid(g[:, H:2 * H]) * cn[:, l] + _sigmoid(g[:, :H]) * np.tanh(g[:, 2 * H:3 * H])
            hn[:, l] = _sigmoid(g[:, 3 * H:]) * np.tanh(c)
            cn[:, l] = c
            inp = hn[:, l]
        new["h_neutral"], new["c_neutral"] = hn, cn
        latent = inp
        # residual style branches, all K at once
        K = len(TARGET_STYLES)
        hs = np.stack([state[f"h_{s}"] for s in TARGET_STYLES], 1)  # (B, K, Ls, H)
        cs = np.stack([state[f"c_{s}"] for s in TARGET_STYLES], 1)
        inp = None
        for l, (Wi, Wh, b) in enumerate(self.branch):
            if l == 0:
                gi = (z @ self.branch0_in).reshape(B, K, 4 * H)
            else:
                gi = np.matmul(inp.transpose(1, 0, 2), Wi).transpose(1, 0, 2)
            g = gi + np.matmul(hs[:, :, l].transpose(1, 0, 2), Wh).transpose(1, 0, 2) + b
            c = _sigmoid(g[..., H:2 * H]) * cs[:, :, l] + _sigmoid(g[..., :H]) * np.tanh(g[..., 2 * H:3 * H])
            hs[:, :, l] = _sigmoid(g[..., 3 * H:]) * np.tanh(c)
            cs[:, :, l] = c
            inp = hs[:, :, l]
        for k, s in enumerate(TARGET_STYLES):
            new[f"h_{s}"], new[f"c_{s}"] = hs[:, k].copy(), cs[:, k].copy()
        latent = latent + (w[:, :, None] * inp).sum(1)
        h = np.concatenate([latent, w], -1)
        for i, (W, b) in enumerate(self.dec):
            h = h @ W + b
            if i < 2:
                h = np.maximum(h, 0.0)
        return h, new

    # ------------------------------------------------------------------ offline helpers

    def torch_generator(self):
        """The same weights as a torch `Generator` (for whole-clip runs and tests)."""
        import torch

        from .model import ERDConfig, Generator
        cfg = ERDConfig(**self.config)
        gen = Generator(cfg, self.mean, self.std)
        state = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in self.p.items()}
        state["mean"], state["std"] = torch.as_tensor(self.mean, dtype=torch.float32), torch.as_tensor(self.std, dtype=torch.float32)
        gen.load_state_dict(state)
        return gen.eval()

    def stylise_stream(self, motion, weights: np.ndarray, content: str | None = None, input_style: str | None = None):
        """Run a whole Motion through step_batch frame by frame (batch 1); returns a Motion."""
        from dataclasses import replace
        state = self.init_state(1, content=content, input_style=input_style)
        w = np.asarray(weights, np.float64)
        roots, rots = [], []
        for t in range(motion.num_frames):
            wt = w[t] if w.ndim == 2 else w
            out, state = self.step_batch(state, FrameBatch(motion.translations[t:t + 1, 1], motion.rotations[t:t + 1]), wt[None])
            roots.append(out.root[0])
            rots.append(out.rotations[0])
        trans = motion.translations.copy()
        trans[:, 1] = np.array(roots)
        return replace(motion, rotations=np.array(rots), translations=trans)


def load(weights_dir: Path) -> ERDModel:
    weights_dir = Path(weights_dir)
    config = json.loads((weights_dir / "config.json").read_text())
    with np.load(weights_dir / WEIGHTS_FILE) as z:
        arrays = {k: z[k] for k in z.files}
    skeleton = Skeleton(tuple(str(n) for n in arrays.pop("skeleton_names")), arrays.pop("skeleton_parents").astype(int),
                        arrays.pop("skeleton_offsets"), arrays.pop("skeleton_end_sites"))
    mean, std, ref = arrays.pop("norm_mean"), arrays.pop("norm_std"), arrays.pop("ref")
    return ERDModel(arrays, config["model"], skeleton, mean, std, ref, meta=config)


def export_weights(ckpt_path: Path, out_dir: Path | None = None, skeleton: Skeleton | None = None) -> Path:
    """Write models/weights/erd/{erd.npz, config.json} from a training checkpoint."""
    import torch

    from ..settings import REPO_ROOT
    out_dir = Path(out_dir or REPO_ROOT / "models" / "weights" / "erd")
    out_dir.mkdir(parents=True, exist_ok=True)
    ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    if skeleton is None:
        from ..data import build_index, load_motion, select
        skeleton = load_motion(select(build_index(["bandai-namco-2"]), split="val")[0]).skeleton
    sd = ck["generator"]
    arrays = {k: v.numpy().astype(np.float32) for k, v in sd.items() if k not in ("mean", "std")}
    np.savez_compressed(out_dir / WEIGHTS_FILE, **arrays, norm_mean=sd["mean"].numpy(), norm_std=sd["std"].numpy(),
                        ref=np.asarray(ck["ref"], np.float64), skeleton_names=np.array(skeleton.names),
                        skeleton_parents=skeleton.parents, skeleton_offsets=skeleton.offsets,
                        skeleton_end_sites=skeleton.end_sites)
    hist = ck.get("history", [])
    config = {"model": ck["model_config"], "styles": list(TARGET_STYLES), "input_styles": list(STYLES),
              "contents": list(CONTENTS), "iterations": ck["iter"], "train_seconds": round(ck["seconds"], 1),
              "train_config": ck["train_config"], "classifier_val_acc": ck.get("classifier_val_acc"),
              "final_validation": hist[-1] if hist else None, "licence": "CC BY-NC 4.0 (inherited from Bandai Namco dataset 2)"}
    (out_dir / "config.json").write_text(json.dumps(config, indent=1))
    return out_dir
