"""The BVH tools on any humanoid rig: `stylestream stylise`, `retarget` and `render` take a rig made
from a Bandai Namco walk (Z up, metres, A-pose rest, twist bones, fingers) and give the same
hierarchy back, or one line naming what is missing."""

from __future__ import annotations

import numpy as np
import pytest

from clients.cli import main
from models.motion import bvh
from models.motion.skeleton import from_bvh, to_bvh
from models.registry import load_models
from models.settings import get_settings

from .clips import angle_deg
from .live_server import live_server
from .rigs import SPECS, make_rig


@pytest.fixture(scope="module")
def server():
    with live_server({"lti": load_models(get_settings().weights_dir)["lti"]}) as (base, _):
        yield base


@pytest.fixture(scope="module")
def rig_bvh(bn_walk, tmp_path_factory):
    motion = make_rig(bn_walk.slice(0, 60), SPECS["ue5"])
    motion.euler_orders = tuple("XYZ" for _ in motion.skeleton.names)
    path = tmp_path_factory.mktemp("rig") / "ue5_walk.bvh"
    bvh.write(to_bvh(motion), path)
    return path


def test_stylise_a_made_rig_keeps_its_hierarchy(server, rig_bvh, tmp_path):
    out, sheet = tmp_path / "out.bvh", tmp_path / "out.png"
    assert (
        main(["stylise", str(rig_bvh), "--url", server, "--style", "elderly", "-o", str(out), "--render", str(sheet)])
        == 0
    )
    source, written = bvh.read(rig_bvh), bvh.read(out)
    assert [(j.name, j.channels) for j in written.joints] == [(j.name, j.channels) for j in source.joints]
    inp, got = from_bvh(source), from_bvh(written)
    fingers = [inp.skeleton.index(n) for n in ("index_01_l", "index_02_l", "thumb_01_r")]
    assert angle_deg(got.rotations[:, fingers], inp.rotations[:, fingers]).max() < 1e-3  # passed through
    assert angle_deg(got.rotations, inp.rotations).mean() > 1.0  # stylised
    assert sheet.stat().st_size > 10_000


def test_retarget_and_render_a_made_rig(rig_bvh, tmp_path):
    out = tmp_path / "bn.bvh"
    assert main(["retarget", str(rig_bvh), "-o", str(out)]) == 0
    bn = from_bvh(bvh.read(out))
    assert "Hips" in bn.skeleton.names and bn.num_frames == 60
    head = bn.global_positions()[:, bn.skeleton.index("Head")]
    assert np.all(head[:, 1] > 120.0)  # upright, Y up in cm, though the file is Z up
    png = tmp_path / "r.png"
    assert main(["render", str(rig_bvh), str(out), "--retarget", "-o", str(png), "--frames", "2"]) == 0
    assert png.stat().st_size > 5_000


def test_a_rig_without_legs_ends_in_one_line(rig_bvh, tmp_path, capsys):
    legless = tmp_path / "legless.bvh"
    legless.write_text(rig_bvh.read_text().replace("thigh_", "wing_").replace("calf_", "fin_"))
    assert main(["retarget", str(legless), "-o", str(tmp_path / "x.bvh")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stylestream retarget: error:") and "upperleg_l" in err and "lowerleg_r" in err
    assert "Traceback" not in err and len(err.splitlines()) == 1
