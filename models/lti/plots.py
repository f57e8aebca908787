"""Figures: DTW vs IMW alignment of one normal/elderly walk pair (cf. Hsu et al. 2005, Fig. 2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import representation as rep


def alignment_figure(path: Path, style: str = "elderly", content: str = "walk") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from models.data import build_index, load_motion

    from .train import CONFIG, make_pairs, match_features, matching_stats, reference_rotations
    from .warping import dtw_warp, imw

    index = build_index(CONFIG["datasets"])
    a, b = next(p for p in make_pairs(index, style, "train") if p[1].content == content)
    ref = reference_rotations(index)
    mean, std = matching_stats(index, ref)
    x = match_features(rep.motion_to_features(load_motion(a), ref), mean, std)
    y = match_features(rep.motion_to_features(load_motion(b), ref), mean, std)
    w_dtw = dtw_warp(x, y)
    res = imw(x, y, **CONFIG["imw"])
    names = ["height", "tilt.x", "tilt.y", "tilt.z"] + [f"{j}.{c}" for j in range(2, 22) for c in "xyz"]
    knee = [names.index(f"15.{c}") for c in "xyz"]
    dof = max(knee, key=lambda d: x[:, d].var())  # the knee's flexion axis
    t = np.arange(len(x))

    def at(w):
        return np.interp(w, np.arange(len(y)), y[:, dof])

    fig, ax = plt.subplots(3, 1, figsize=(10, 10))
    ax[0].plot(t, x[:, dof], "k", lw=2, label=f"input ({a.style}) {a.name}")
    ax[0].plot(
        np.arange(len(y)) * (len(x) - 1) / (len(y) - 1),
        y[:, dof],
        "0.6",
        label=f"output ({b.style}), linearly stretched",
    )
    ax[0].plot(t, at(w_dtw), "tab:blue", label="output, DTW-aligned")
    ax[0].plot(t, at(res.warp), "tab:red", label="output, IMW-aligned")
    ax[0].set_title(f"DOF {names[dof]} (LowerLeg_L expmap, normalised)")
    ax[0].legend(fontsize=8)
    ax[1].plot(t, w_dtw, "tab:blue", label="DTW")
    ax[1].plot(t, res.warp, "tab:red", label="IMW (slope-limited, space-warped)")
    ax[1].set_xlabel("input frame")
    ax[1].set_ylabel("output frame")
    ax[1].legend()
    ax[1].set_title("time warps")
    ax[2].plot(res.objective, "o-")
    ax[2].set_title("IMW objective after each stage (time, space, time, ...)")
    ax[2].set_yscale("log")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
