"""Figure-4 analogue of Mason et al. 2022: per style, a foot (contact source) and a hand
(contact-free source): the source curve, the normalised low-passed signal, the per-frame
sinusoid fits, and the resulting phase over a few seconds of walk."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .phases import local_phases, style_axes

# (dataset, style): three dataset-2 walks of contrasting rhythm and one dataset-1 style
DEFAULT_STYLES: tuple[tuple[str, str], ...] = (
    ("bandai-namco-2", "normal"),
    ("bandai-namco-2", "elderly"),
    ("bandai-namco-2", "exhausted"),
    ("bandai-namco-1", "chimpira"),
)


def phases_figure(
    path: Path,
    styles: tuple[tuple[str, str], ...] = DEFAULT_STYLES,
    content: str = "walk",
    bones: tuple[str, str] = ("Foot_L", "Hand_L"),
    seconds: float = 4.0,
    start_s: float = 1.0,
    split: str = "train",
) -> Path:
    """Write the figure to `path`; hands are centred per style and gait (all `split` clips of the
    style and content), the longest clip of each style is shown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from models.data import build_index, load_motion, select

    index = build_index(sorted({d for d, _ in styles}))
    fig, axs = plt.subplots(
        2 * len(styles),
        len(bones),
        figsize=(7 * len(bones), 2.6 * 2 * len(styles)),
        gridspec_kw={"height_ratios": [2, 1] * len(styles)},
        squeeze=False,
    )
    for r, (dataset, style) in enumerate(styles):
        clips = select(index, dataset=dataset, style=style, content=content, split=split)
        motions = [load_motion(c) for c in clips]
        k = int(np.argmax([m.rotations.shape[0] for m in motions]))
        lp = local_phases(motions[k], axes=style_axes(motions))
        fps = lp.fps
        F = lp.phase.shape[0]
        a = min(int(start_s * fps), max(F - int(seconds * fps), 0))
        sl = slice(a, min(F, a + int(seconds * fps)))
        t = np.arange(F)[sl] / fps
        for c, bone in enumerate(bones):
            i = lp.bones.index(bone)
            top, bot = axs[2 * r, c], axs[2 * r + 1, c]
            if bone.startswith("Foot"):
                contact = lp.contacts[sl, 0 if bone.endswith("_L") else 1]
                top.fill_between(t, -2.5, 2.5, where=contact, color="0.88", step="mid", label="contact (source)")
            else:
                src = lp.source[sl, i]
                span = np.ptp(src) or 1.0
                top.plot(
                    t, 2 * (src - src.min()) / span - 1, color="0.6", lw=1, label="PC1 position (source, rescaled)"
                )
            top.plot(t, lp.signal[sl, i], "k", lw=2, label="normalised + Butterworth")
            top.plot(t, lp.fitted()[sl, i], "r--", lw=1.5, label="fit a sin(ft-s)+b at each frame")
            # a few whole-window fits (1.5 s), to show the sinusoid each frame was fitted with
            for j in range(sl.start + 22, sl.stop - 22, 30):
                tw = np.arange(j - 22, j + 23) / fps
                y = (
                    lp.fit_amplitude[j, i] * np.sin(lp.phase[j, i] + 2 * np.pi * lp.frequency[j, i] * (tw - j / fps))
                    + lp.offset[j, i]
                )
                top.plot(tw, y, color="tab:orange", lw=0.8, alpha=0.8)
            top.set_ylim(-2.5, 2.5)
            f_med = float(np.median(lp.frequency[sl, i]))
            top.set_title(f"{dataset[-1]}:{style} {bone} ({clips[k].name}) median f={f_med:.2f} Hz", fontsize=9)
            if r == 0:
                top.legend(fontsize=7, loc="upper right", ncol=2)
            bot.plot(t, lp.phase[sl, i] / (2 * np.pi), "tab:blue", lw=1.5, label="phase / 2pi")
            bot.plot(
                t,
                lp.features[sl, i, 0] / max(lp.amplitude[sl, i].max(), 1e-9) * 0.5 + 0.5,
                color="tab:green",
                lw=0.8,
                label="A sin(phase), scaled",
            )
            bot.set_ylim(-0.05, 1.05)
            ax2 = bot.twinx()
            ax2.plot(t, lp.amplitude[sl, i], color="tab:purple", lw=1, label="amplitude A")
            ax2.set_ylim(0, max(3.0, float(lp.amplitude[sl, i].max()) * 1.1))
            ax2.tick_params(labelsize=7)
            if r == 0:
                bot.legend(fontsize=7, loc="upper left")
                ax2.legend(fontsize=7, loc="upper right")
            if r == len(styles) - 1:
                bot.set_xlabel("time (s)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=70)
    plt.close(fig)
    return path
