"""Renders of motions with matplotlib (Agg): PNG contact sheets and animated GIFs.

Limbs are ribbons between FK positions; head, hands and feet are solids posed by world rotations
(`orientation.py`), so a head turned backwards or a twisted wrist shows. Left limbs red, right
blue; the camera follows the root. Sizes come from the motion, so any skeleton works, and a Z-up
humanoid is drawn standing (`upright`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import PillowWriter  # noqa: E402
from matplotlib.colors import to_rgb  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from .humanoid import RigError, humanoid_rig, in_model_world  # noqa: E402
from .orientation import FACES, Solid, face_normals, joint_sides, rig, solid_corners  # noqa: E402
from .skeleton import Motion, Skeleton  # noqa: E402

__all__ = ["joint_sides", "render_contact_sheet", "render_gif", "up_axis", "upright"]

LEFT, RIGHT, CENTRE = "tab:red", "tab:blue", "0.15"
HEAD, MARK = "0.8", "0.05"  # the head block, and the nose / thumb stubs on it and the hands
LEGEND = "left red, right blue; black nose = where the face looks, black stub = thumb, dark face = palm"


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
    return [
        (int(p), j, colour[int(sides[j])])
        for j, p in enumerate(skeleton.parents)
        if p >= 0 and body[p] and np.linalg.norm(skeleton.offsets[j]) > 1e-6
    ]


def _as_list(motions: Motion | Sequence[Motion]) -> list[Motion]:
    return [motions] if isinstance(motions, Motion) else list(motions)


def up_axis(motion: Motion) -> str:
    """'y' or 'z': up as the rest pose says (`humanoid.detect_up`), else as the frames do; default 'y'."""
    try:
        hr = humanoid_rig(motion.skeleton)
    except RigError:
        return "y"
    if hr.up_detected:
        return hr.up
    pos = motion.global_positions()
    roles = hr.roles
    v = np.median(pos[:, roles["head"]] - 0.5 * (pos[:, roles["foot_l"]] + pos[:, roles["foot_r"]]), axis=0)
    return "z" if v[2] > max(abs(v[1]), abs(v[0])) else "y"


def upright(motion: Motion, up: str | None = None) -> Motion:
    """The motion in a Y-up world as the renderer draws it (a Z-up humanoid turned, in cm)."""
    up = up or up_axis(motion)
    if up == "y":
        return motion
    try:
        hr = humanoid_rig(motion.skeleton, up=up)
    except RigError:
        return motion
    return in_model_world(motion, hr)


def face_tints(solids: Sequence[Solid]) -> np.ndarray:
    """(S, 6, 3) face colours that show a part rolled about its own axis (light front, dark palm, sole)."""
    base = {1: to_rgb(LEFT), -1: to_rgb(RIGHT), 0: to_rgb(HEAD)}
    out = np.empty((len(solids), 6, 3))
    for i, s in enumerate(solids):
        c = np.array(to_rgb(MARK) if s.mark else base[s.side])
        out[i] = c
        if s.mark:
            continue
        kind = s.part.split("_")[0]
        if kind == "head":
            out[i, 1] = (0.96, 0.87, 0.74)  # the face
        elif kind == "hand":
            out[i, 5 if s.side > 0 else 4] = 0.45 * c
        elif kind in ("foot", "toe"):
            out[i, 3], out[i, 2] = 0.45 * c + 0.55, 0.4 * c
    return out


def eye_direction(view: tuple[float, float]) -> np.ndarray:
    """World (Y up) unit vector from the scene toward the camera of a matplotlib `view` (elev, azim)."""
    elev, azim = np.radians(view)
    return np.array([np.cos(elev) * np.cos(azim), np.sin(elev), -np.cos(elev) * np.sin(azim)])  # mpl (x, y, z) -> world


def bone_ribbons(a: np.ndarray, b: np.ndarray, eye: np.ndarray, width: float) -> np.ndarray:
    """(B, 4, 3) flat quads from `a` to `b` facing `eye`, depth-sorted with the solids."""
    side = np.cross(b - a, eye)
    side *= 0.5 * width / np.maximum(np.linalg.norm(side, axis=-1, keepdims=True), 1e-12)
    return np.stack([a - side, a + side, b + side, b - side], axis=1)


class _Panel:
    """One 3D axes showing one skeleton; `show(frame)` poses the figure and moves camera and grid."""

    def __init__(
        self,
        ax: Any,
        motion: Motion,
        transforms: tuple[np.ndarray, np.ndarray],
        view: tuple[float, float],
        title: str = "",
    ) -> None:
        self.ax, self.root = ax, _root_index(motion.skeleton)
        self.body = _body(motion.skeleton)
        self.rotations, self.positions = transforms
        rel = self.positions[:, self.body] - self.positions[:, self.root : self.root + 1]
        self.radius = 1.15 * float(np.percentile(np.linalg.norm(rel, axis=-1).max(axis=1), 90)) or 1.0
        self.spacing = self.radius / 2.0
        bones = _bones(motion.skeleton)
        self.bones = np.array([[p, c] for p, c, _ in bones], int).reshape(-1, 2)
        self.solids = rig(motion)
        self.eye = eye_direction(view)
        light = self.eye + np.array([0.0, 0.8, 0.0])  # above and behind the camera
        self.light = light / np.linalg.norm(light)
        self.width = 0.025 * self.radius  # with its edges, about a 2-point line on the default panels
        # limbs (flat ribbons) and solids in one collection, painted far to near
        bone_rgb = np.array([to_rgb(c) for _, _, c in bones]).reshape(-1, 3)
        self.tints = np.concatenate([bone_rgb, face_tints(self.solids).reshape(-1, 3)])
        self.lit = np.concatenate([np.zeros(len(bones), bool), np.ones(6 * len(self.solids), bool)])
        edges = np.concatenate(
            [np.c_[bone_rgb, np.ones(len(bones))], np.tile((0.1, 0.1, 0.1, 0.6), (6 * len(self.solids), 1))]
        )
        ax.computed_zorder = False  # ground under the figure, whatever matplotlib thinks of their depths
        self.grid = ax.plot([], [], [], color="0.75", lw=0.6, zorder=1)[0]
        self.shadow = ax.plot([], [], [], color="0.55", lw=1.0, alpha=0.6, zorder=1.1)[0]
        quads, colours = self._polygons(0)
        # one line width for all: matplotlib depth-sorts face and edge colours, not widths
        self.figure = Poly3DCollection(quads, facecolors=colours, edgecolors=edges, linewidths=0.5, zorder=2)
        ax.add_collection3d(self.figure)
        ax.set_box_aspect((1, 1, 1), zoom=1.45)
        ax.view_init(elev=view[0], azim=view[1])
        ax.set_axis_off()
        if title:
            ax.set_title(title, fontsize=8, pad=0)

    @staticmethod
    def _xyz(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World (X, Y up, Z) -> matplotlib (x, y, z up), keeping the frame right-handed."""
        return p[..., 0], -p[..., 2], p[..., 1]

    def _polygons(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Limb ribbons then solid faces at `frame` as quads (N, 4, 3), and their lit RGB."""
        pos = self.positions[frame]
        ribbons = bone_ribbons(pos[self.bones[:, 0]], pos[self.bones[:, 1]], self.eye, self.width)
        corners = solid_corners(self.rotations[frame], pos, self.solids) if self.solids else np.zeros((0, 8, 3))
        lit = 0.55 + 0.45 * np.clip(face_normals(corners) @ self.light, 0.0, 1.0)  # (S, 6)
        quads = np.concatenate([ribbons, corners[:, FACES].reshape(-1, 4, 3)])
        shade = np.ones(len(quads))
        shade[self.lit] = lit.ravel()
        return np.stack(self._xyz(quads), axis=-1), np.clip(self.tints * shade[:, None], 0.0, 1.0)

    def show(self, frame: int) -> list:
        pos = self.positions[frame]
        cx, cz, r = pos[self.root, 0], pos[self.root, 2], self.radius
        quads, colours = self._polygons(frame)
        self.figure.set_verts(quads)
        self.figure.set_facecolor(colours)
        # ground grid: world-fixed lines at multiples of `spacing` inside the view box
        segs = []
        for axis, centre, other in ((0, cx, cz), (2, cz, cx)):
            v = (
                np.arange(np.ceil((centre - r) / self.spacing), np.floor((centre + r) / self.spacing) + 1)
                * self.spacing
            )
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
        return [self.figure, self.shadow, self.grid]


def render_contact_sheet(
    motions: Motion | Sequence[Motion],
    path: str | Path,
    frames: int | Sequence[int] = 8,
    titles: Sequence[str] | None = None,
    view: tuple[float, float] = (10.0, -60.0),
    panel_size: float = 1.9,
    dpi: int = 80,
    columns: int = 6,
    up: str | None = None,
) -> Path:
    """PNG of poses: `frames` a count or indices; one motion in a grid, several one row each."""
    motions = [upright(m, up) for m in _as_list(motions)]
    titles = list(titles) if titles is not None else [""] * len(motions)
    n_frames = frames if isinstance(frames, int) else len(frames)
    if len(motions) == 1:
        n_cols = min(n_frames, columns)
        n_rows = -(-n_frames // n_cols)
    else:
        n_cols, n_rows = n_frames, len(motions)
    fig = plt.figure(figsize=(panel_size * n_cols, panel_size * n_rows + 0.3), dpi=dpi)
    for m, motion in enumerate(motions):
        transforms = motion.global_transforms()
        if isinstance(frames, int):
            idx = np.linspace(0, motion.num_frames - 1, frames).round().astype(int)
        else:
            idx = np.clip(np.asarray(frames, int), 0, motion.num_frames - 1)
        for k, f in enumerate(idx):
            slot = m * n_cols + k if len(motions) > 1 else k
            ax = fig.add_subplot(n_rows, n_cols, slot + 1, projection="3d")
            label = f"{titles[m]}  " if k == 0 and titles[m] else ""
            _Panel(ax, motion, transforms, view, f"{label}f{f} ({f / motion.fps:.1f}s)").show(int(f))
    fig.suptitle(LEGEND, fontsize=7, y=0.995)
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
    up: str | None = None,
) -> Path:
    """Animated GIF of the motions side by side at `fps`, at most `seconds` long."""
    motions = [upright(m, up) for m in _as_list(motions)]
    titles = list(titles) if titles is not None else [""] * len(motions)
    fps = min(fps, min(m.fps for m in motions))
    duration = min(seconds, max((m.num_frames - 1) / m.fps for m in motions))
    times = np.arange(int(np.floor(duration * fps + 1e-9)) + 1) / fps
    fig = plt.figure(figsize=(panel_size * len(motions), panel_size), dpi=dpi)
    panels, indices = [], []
    for k, motion in enumerate(motions):
        ax = fig.add_subplot(1, len(motions), k + 1, projection="3d")
        panels.append(_Panel(ax, motion, motion.global_transforms(), view, titles[k]))
        indices.append(np.clip(np.round(times * motion.fps).astype(int), 0, motion.num_frames - 1))
    fig.text(0.5, 0.005, LEGEND, ha="center", va="bottom", fontsize=5.5, color="0.3")
    fig.subplots_adjust(left=0, right=1, bottom=0.03, top=0.92, wspace=0)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = PillowWriter(fps=round(fps))
    with writer.saving(fig, str(path), dpi):
        for i in range(len(times)):
            for panel, idx in zip(panels, indices):
                panel.show(int(idx[i]))
            writer.grab_frame()
    plt.close(fig)
    return path
