"""Top-down footprint plots: the picture behind the skate number. Each foot's ankle path on the
ground plane, with its flat-foot contact frames (`metrics.flat_foot_contacts`) as dots coloured
by foot speed: a planted foot is a tight cluster of green dots, a sliding one a red streak."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from ..motion.features import body_joint, left_leg_length  # noqa: E402
from ..motion.skeleton import Motion  # noqa: E402
from .metrics import SKATE_SPEED, flat_foot_contacts, foot_skating  # noqa: E402


def render_footprints(
    motions: Sequence[Motion],
    path: str | Path,
    titles: Sequence[str] | None = None,
) -> Path:
    """One top-down panel per motion (x right, z up, equal axes); returns the PNG path."""
    titles = list(titles) if titles is not None else [""] * len(motions)
    fig, axes = plt.subplots(1, len(motions), figsize=(3.2 * len(motions), 3.6), dpi=90, squeeze=False)
    for ax, motion, title in zip(axes[0], motions, titles):
        pos = motion.global_positions()
        contacts, speeds = flat_foot_contacts(motion, pos)
        limit = SKATE_SPEED * left_leg_length(motion.skeleton)
        for k, side in enumerate("lr"):
            ankle = pos[:, body_joint(motion.skeleton, f"ankle_{side}")]
            ax.plot(ankle[:, 0], ankle[:, 2], lw=0.4, color="0.7")
            on = contacts[:, k]
            ax.scatter(
                ankle[on, 0], ankle[on, 2], s=4, c=speeds[on, k], cmap="RdYlGn_r", vmin=0, vmax=2 * limit, linewidths=0
            )
        skate = foot_skating(motion, pos)["skate_ratio"]
        ax.set_title(f"{title}\nskate {skate:.0%} (red = over {limit:.0f}/s)", fontsize=7)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=5)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
