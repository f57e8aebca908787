"""Stick-figure renders of motions with matplotlib (Agg): PNG contact sheets and animated GIFs.

Figures are drawn from FK world positions, world Y up shown as the vertical axis, with a ground
grid at height 0 and a camera that follows the root. Left limbs are red, right limbs blue, the
spine black. Works for any skeleton (Bandai Namco in cm, CMU in its own units): sizes are taken
from the motion itself.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import PillowWriter  # noqa: E402

from .skeleton import Motion, Skeleton  # noqa: E402

LEFT, RIGHT, CENTRE = "tab:red", "tab:blue", "0.15"
_LEFT = re.compile(r"(_L$|^Left|^L(?=[A-Z])|^lhand$)")
_RIGHT = re.compile(r"(_R$|^Right|^R(?=[A-Z])|^rhand$)")


def joint_sides(skeleton: Skeleton) -> np.ndarray:
    """+1 for left joints, -1 for right joints, 0 for the centre line (from joint names)."""
    return np.array([1 if _LEFT.search(n) else -1 if _RIGHT.search(n) else 0 for n in skeleton.names])


def _root_index(skeleton: Skeleton) -> int:
    """The body's root: Hips (Bandai Namco hangs it under a static `joint_Root` at the origin)."""
    return skeleton.index("Hips") if "Hips" in skeleton.names else 0


def _body(skeleton: Skeleton) -> np.ndarray:
    """Mask of the joints in the body root's subtree (drops BN's static `joint_Root`)."""
    keep = np.zeros(skeleton.num_joints, bool)
    keep[_root_index(skeleton)] = True
    for j, p in enumerate(skeleton.parents):
        keep[j] |= p >= 0 and keep[p]
    return keep


def _bones(skeleton: Skeleton) -> list[tuple[int, int, str]]:
    """(parent, child, colour) for every bone of non-zero length inside the body."""
    sides, body = joint_sides(skeleton), _body(skeleton)
    colour = {1: LEFT, -1: RIGHT, 0: CENTRE}
    return [(int(p), j, colour[int(sides[j])]) for j, p in enumerate(skeleton.parents)
            if p >= 0 and body[p] and np.linalg.norm(skeleton.offsets[j]) > 1e-6]


def _as_list(motions: Motion | Sequence[Motion]) -> list[Motion]:
    return [motions] if isinstance(motions, Motion) else list(motions)


class _Panel:
    """One 3D axes showing one skeleton; `show(frame)` poses the figure and moves camera and grid."""

    def __init__(self, ax, motion: Motion, positions: np.ndarray, view: tuple[float, float], title: str = ""):
        self.ax, self.root = ax, _root_index(motion.skeleton)
        self.body = _body(motion.skeleton)
        self.positions = positions
        rel = positions[:, self.body] - positions[:, self.root : self.root + 1]
        self.radius = 1.15 * float(np.percentile(np.linalg.norm(rel, axis=-1).max(axis=1), 90)) or 1.0
        self.spacing = self.radius / 2.0
        # one line artist per colour (bones separated by NaN) and one for the grid: few artists draw fast
        bones = _bones(motion.skeleton)
        self.groups = []
        for colour in (CENTRE, LEFT, RIGHT):
            pairs = [(p, c) for p, c, col in bones if col == colour]
            if pairs:
                order = np.array([[p, c, -1] for p, c in pairs]).ravel()
                self.groups.append((order, ax.plot([], [], [], color=colour, lw=2.0, solid_capstyle="round")[0]))
        self.joints = ax.plot([], [], [], "o", color="0.3", ms=1.8)[0]
        self.grid = ax.plot([], [], [], color="0.75", lw=0.6)[0]
        self.shadow = ax.plot([], [], [], color="0.55", lw=1.0, alpha=0.6)[0]
        ax.set_box_aspect((1, 1, 1), zoom=1.45)
        ax.view_init(elev=view[0], azim=view[1])
        ax.set_axis_off()
        if title:
            ax.set_title(title, fontsize=8, pad=0)

    @staticmethod
    def _xyz(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World (X, Y up, Z) -> matplotlib (x, y, z up), keeping the frame right-handed."""
        return p[..., 0], -p[..., 2], p[..., 1]

    def show(self, frame: int) -> list:
        pos = self.positions[frame]
        cx, cz, r = pos[self.root, 0], pos[self.root, 2], self.radius
        padded = np.concatenate([pos, np.full((1, 3), np.nan)])  # index -1 -> NaN breaks the line
        for order, line in self.groups:
            line.set_data_3d(*self._xyz(padded[order]))
        self.joints.set_data_3d(*self._xyz(pos[self.body]))
        # ground grid: world-fixed lines at multiples of `spacing` inside the view box
        segs = []
        for axis, centre, other in ((0, cx, cz), (2, cz, cx)):
            v = np.arange(np.ceil((centre - r) / self.spacing), np.floor((centre + r) / self.spacing) + 1) * self.spacing
            seg = np.full((len(v), 3, 3), np.nan)
            seg[:, :2, 1] = 0.0
            seg[:, :2, axis] = v[:, None]
            seg[:, 0, 2 - axis], seg[:, 1, 2 - axis] = other - r, other + r
            segs.append(seg.reshape(-1, 3))
        self.grid.set_data_3d(*self._xyz(np.concatenate(segs)))
        # the root's path on the ground, the part inside the view box
        path = self.positions[:, self.root].copy()
        path[:, 1] = 0.0
        outside = (np.abs(path[:, 0] - cx) > r) | (np.abs(path[:, 2] - cz) > r)
        path[outside] = np.nan
        self.shadow.set_data_3d(*self._xyz(path))
        self.ax.set_xlim(cx - r, cx + r)
        self.ax.set_ylim(-cz - r, -cz + r)
        self.ax.set_zlim(0.0, 2 * r)
        return [line for _, line in self.groups] + [self.joints, self.shadow, self.grid]


def render_contact_sheet(
    motions: Motion | Sequence[Motion],
    path: str | Path,
    frames: int | Sequence[int] = 8,
    titles: Sequence[str] | None = None,
    view: tuple[float, float] = (10.0, -60.0),
    panel_size: float = 1.9,
    dpi: int = 80,
    columns: int = 6,
) -> Path:
    """PNG of poses: `frames` is a count spread evenly over each motion, or explicit frame indices
    (clipped to each motion's length). One motion: its poses in a grid `columns` wide. Several
    motions: one row per motion, one column per frame."""
    motions = _as_list(motions)
    titles = list(titles) if titles is not None else [""] * len(motions)
    n_frames = frames if isinstance(frames, int) else len(frames)
    if len(motions) == 1:
        n_cols = min(n_frames, columns)
        n_rows = -(-n_frames // n_cols)
    else:
        n_cols, n_rows = n_frames, len(motions)
    fig = plt.figure(figsize=(panel_size * n_cols, panel_size * n_rows + 0.3), dpi=dpi)
    for m, motion in enumerate(motions):
        positions = motion.global_positions()
        if isinstance(frames, int):
            idx = np.linspace(0, motion.num_frames - 1, frames).round().astype(int)
        else:
            idx = np.clip(np.asarray(frames, int), 0, motion.num_frames - 1)
        for k, f in enumerate(idx):
            slot = m * n_cols + k if len(motions) > 1 else k
            ax = fig.add_subplot(n_rows, n_cols, slot + 1, projection="3d")
            label = f"{titles[m]}  " if k == 0 and titles[m] else ""
            _Panel(ax, motion, positions, view, f"{label}f{f} ({f / motion.fps:.1f}s)").show(int(f))
    fig.suptitle("left red, right blue", fontsize=7, y=0.995)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=1 - 0.3 / (panel_size * n_rows + 0.3), wspace=0, hspace=0.08)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def render_gif(
    motions: Motion | Sequence[Motion],
    path: str | Path,
    fps: float = 15.0,
    seconds: float = 6.0,
    titles: Sequence[str] | None = None,
    view: tuple[float, float] = (10.0, -60.0),
    panel_size: float = 2.6,
    dpi: int = 60,
) -> Path:
    """Animated GIF of the motions side by side, played at `fps` (<= source rate), at most
    `seconds` long; shorter motions hold their last frame."""
    motions = _as_list(motions)
    titles = list(titles) if titles is not None else [""] * len(motions)
    fps = min(fps, min(m.fps for m in motions))
    duration = min(seconds, max((m.num_frames - 1) / m.fps for m in motions))
    times = np.arange(int(np.floor(duration * fps + 1e-9)) + 1) / fps
    fig = plt.figure(figsize=(panel_size * len(motions), panel_size), dpi=dpi)
    panels, indices = [], []
    for k, motion in enumerate(motions):
        ax = fig.add_subplot(1, len(motions), k + 1, projection="3d")
        panels.append(_Panel(ax, motion, motion.global_positions(), view, titles[k]))
        indices.append(np.clip(np.round(times * motion.fps).astype(int), 0, motion.num_frames - 1))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = PillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi):
        for i in range(len(times)):
            for panel, idx in zip(panels, indices):
                panel.show(int(idx[i]))
            writer.grab_frame()
    plt.close(fig)
    return path
