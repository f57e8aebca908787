"""The matplotlib renderer writes real, non-blank images for BN and CMU skeletons."""

from __future__ import annotations

import numpy as np
from PIL import Image

from models.motion.render import joint_sides, render_contact_sheet, render_gif
from models.motion.resample import resample


def _not_blank(img: Image.Image) -> None:
    a = np.asarray(img.convert("RGB"), dtype=float)
    assert a.std() > 5.0
    coloured = (np.abs(a[..., 0] - a[..., 2]) > 60).mean()  # red / blue limbs are drawn
    assert coloured > 0.001


def test_joint_sides(bn_walk, cmu_walk):
    for m in (bn_walk, cmu_walk):
        sides = joint_sides(m.skeleton)
        assert (sides == 1).sum() == (sides == -1).sum() > 0
        assert (sides[m.skeleton.mirror_map()] == -sides).all()
    assert joint_sides(bn_walk.skeleton)[bn_walk.skeleton.index("Hips")] == 0


def test_contact_sheet_png(tmp_path, bn_walk, cmu_walk):
    path = render_contact_sheet([bn_walk.slice(0, 30), resample(cmu_walk.slice(0, 120), 30)], tmp_path / "sheet.png",
                                frames=3, titles=["bn", "cmu"], panel_size=1.5, dpi=50)
    with Image.open(path) as img:
        assert img.format == "PNG" and img.size[0] > 100 and img.size[1] > 100
        _not_blank(img)
    single = render_contact_sheet(bn_walk, tmp_path / "one.png", frames=4, columns=2, panel_size=1.2, dpi=50)
    with Image.open(single) as img:
        assert img.size[1] > img.size[0] * 0.8  # 2 x 2 grid
        _not_blank(img)


def test_gif_is_animated(tmp_path, bn_walk, cmu_walk):
    path = render_gif([bn_walk.slice(0, 30), cmu_walk.slice(0, 120)], tmp_path / "walk.gif", fps=6, seconds=1.0,
                      titles=["bn", "cmu"], panel_size=1.5, dpi=50)
    with Image.open(path) as img:
        assert img.format == "GIF" and img.n_frames >= 5  # 1 s at 6 fps (Pillow may merge equal frames)
        img.seek(3)
        _not_blank(img)
