"""LPN-FiLM weights on disk: `lpn.npz` (float16 parameters, float32 normalisation, FiLM vectors,
skeleton), `config.json`, and `tuned_film.npz` (`tune_builtin.py`), kept apart so a tuning run
rewrites a few KB. The runtime computes in float32."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..motion.skeleton import Skeleton

WEIGHTS_FILE = "lpn.npz"
CONFIG_FILE = "config.json"
TUNED_FILE = "tuned_film.npz"  # `tune_builtin.py`: styles (n,), film (n, 4, H) float32
NORMALISATION = ("X_mean", "X_std", "Y_mean", "Y_std", "S_mean", "S_std", "G_scale")
EXPORT_WINDOWS = 32  # windows per style averaged into its FiLM vector (evenly spread over its training clips)
LICENCE = "CC BY-NC 4.0 (inherited from the Bandai Namco Research Motion datasets 1 and 2)"


def export_weights(ckpt_path: Path, out_dir: Path | None = None, windows: int = EXPORT_WINDOWS) -> Path:
    """Write the weights folder from a checkpoint, each style's FiLM vector its generator's mean."""
    import torch

    from ..motion.assets import bandai_namco_pose
    from ..settings import REPO_ROOT
    from .dataset import DataConfig, load_meta, load_split
    from .network import LPN, LPNConfig
    from .train import StyleClips, style_films

    out_dir = Path(out_dir or REPO_ROOT / "models" / "weights" / "lpn")
    out_dir.mkdir(parents=True, exist_ok=True)
    ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    net = LPN(LPNConfig(**ck["model_config"]))
    net.load_state_dict(ck["model"])
    styles = ck["styles"]
    clips = StyleClips(load_split("train", DataConfig()), 120, np.random.default_rng(0))
    films = style_films(net, clips, list(range(len(styles))), limit=windows)
    skeleton = bandai_namco_pose().skeleton
    arrays = {k: v.numpy().astype(np.float32 if k in NORMALISATION else np.float16) for k, v in ck["model"].items()}
    (out_dir / TUNED_FILE).unlink(missing_ok=True)  # tuned for the previous network: meaningless for this one
    np.savez_compressed(
        out_dir / WEIGHTS_FILE,
        **arrays,
        style_film=np.stack([films[k].numpy() for k in range(len(styles))]).astype(np.float32),
        skeleton_names=np.array(skeleton.names),
        skeleton_parents=skeleton.parents,
        skeleton_offsets=skeleton.offsets,
        skeleton_end_sites=skeleton.end_sites,
    )
    hist = ck.get("history", [])
    meta = load_meta(DataConfig())
    config = {
        "model": ck["model_config"],
        "styles": styles,
        "held_out": meta["held_out"],
        "iterations": ck["iter"],
        "train_seconds": round(ck["seconds"], 1),
        "train_config": ck["train_config"],
        "data": {k: meta[k] for k in ("train", "val", "heldout")},
        "final_validation": hist[-1] if hist else None,
        "licence": LICENCE,
    }
    (out_dir / CONFIG_FILE).write_text(json.dumps(config, indent=1))
    return out_dir


def read_weights(weights_dir: Path, tuned: bool = True) -> tuple[dict[str, np.ndarray], Skeleton, dict]:
    """(arrays as float32, skeleton, config); with `tuned`, the tuned built-in vectors applied."""
    weights_dir = Path(weights_dir)
    config = json.loads((weights_dir / CONFIG_FILE).read_text())
    with np.load(weights_dir / WEIGHTS_FILE) as z:
        arrays = {k: z[k] for k in z.files}
    if tuned and (weights_dir / TUNED_FILE).exists():
        arrays["style_film"] = apply_tuned(arrays["style_film"], config["styles"], weights_dir / TUNED_FILE)
    skeleton = Skeleton(
        tuple(str(n) for n in arrays.pop("skeleton_names")),
        arrays.pop("skeleton_parents").astype(int),
        arrays.pop("skeleton_offsets"),
        arrays.pop("skeleton_end_sites"),
    )
    return {k: v.astype(np.float32) for k, v in arrays.items()}, skeleton, config


def apply_tuned(films: np.ndarray, styles: list[str], path: Path) -> np.ndarray:
    """(S, 4, H) exported style vectors with the tuned ones in `path` in their styles' rows."""
    out = np.array(films, np.float32)
    with np.load(path) as z:
        for name, film in zip(z["styles"], z["film"]):
            if str(name) not in styles:
                raise ValueError(f"{path}: {name!r} is not a style of these weights")
            out[styles.index(str(name))] = film.reshape(out.shape[1:])
    return out
