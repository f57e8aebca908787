"""`stylestream stylise in.bvh -o out.bvh`: a real Bandai Namco BVH streamed through a live server.
The written file keeps the input's hierarchy and length and holds exactly what the server sent
back; what a user gets wrong (a file that is not BVH, an unknown style, no server) ends in one
line and exit status 2, not a traceback."""

from __future__ import annotations

import numpy as np
import pytest

from clients.cli import main
from clients.sdk import Client
from models.data import select
from models.motion import bvh
from models.motion.skeleton import from_bvh
from models.registry import load_models
from models.settings import get_settings

from .clips import angle_deg
from .live_server import live_server

FRAMES = 90


@pytest.fixture(scope="module")
def server():
    with live_server({"lti": load_models(get_settings().weights_dir)["lti"]}) as (base, _):
        yield base


@pytest.fixture(scope="module")
def walk_bvh(index, tmp_path_factory):
    """The first 3 s of a validation-split neutral walk, as a BVH file."""
    clip = select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0]
    text = clip.path.read_text()
    header, motion = text.split("MOTION", 1)
    lines = motion.strip().splitlines()
    frame_time = lines[1]
    path = tmp_path_factory.mktemp("bvh") / "walk.bvh"
    path.write_text(
        header + "MOTION\n" + f"Frames: {FRAMES}\n" + frame_time + "\n" + "\n".join(lines[2 : 2 + FRAMES]) + "\n"
    )
    return path


def test_the_written_file_is_the_servers_output_on_the_inputs_hierarchy(server, walk_bvh, tmp_path):
    out, sheet = tmp_path / "walk_elderly.bvh", tmp_path / "walk_elderly.png"
    assert (
        main(
            [
                "stylise",
                str(walk_bvh),
                "--url",
                server,
                "--model",
                "lti",
                "--style",
                "elderly",
                "-o",
                str(out),
                "--render",
                str(sheet),
            ]
        )
        == 0
    )
    source, written = bvh.read(walk_bvh), bvh.read(out)
    assert [(j.name, j.channels) for j in written.joints] == [(j.name, j.channels) for j in source.joints]
    inp, got = from_bvh(source), from_bvh(written)
    assert got.num_frames == inp.num_frames == FRAMES

    header = walk_bvh.read_text().split("MOTION")[0]
    with Client(server).session(model="lti", style="elderly", bvh_header=header, fps=inp.fps) as session:
        replies = [session.stylise(inp.translations[t, 1], inp.rotations[t]) for t in range(FRAMES)]
    expected = np.stack([r.rotations for r in replies])
    assert angle_deg(got.rotations, expected).max() < np.degrees(1e-3)  # as sent, up to the file's printed decimals
    assert np.abs(got.translations[:, 1] - np.stack([r.root for r in replies])).max() < 1e-3
    assert angle_deg(got.rotations, inp.rotations).mean() > 1.0  # and stylised, not copied
    assert sheet.stat().st_size > 10_000


@pytest.mark.parametrize(
    "case, expected",
    [
        ("not_bvh", "unexpected token"),
        ("unknown_style", "unknown_style"),
        ("no_server", "Connection refused"),
    ],
)
def test_user_errors_end_in_one_line_and_status_2(server, walk_bvh, tmp_path, capsys, case, expected):
    source, url, style = walk_bvh, server, "elderly"
    if case == "not_bvh":
        source = tmp_path / "frames.json"
        source.write_text('{"frames": []}')
    elif case == "unknown_style":
        style = "sleepy"
    else:
        url = "http://127.0.0.1:1"
    assert main(["stylise", str(source), "--url", url, "--style", style, "-o", str(tmp_path / "o.bvh")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stylestream stylise: error:") and expected in err
    assert "Traceback" not in err and len(err.splitlines()) == 1


def test_a_file_travelling_on_its_root_joint_is_styled_with_its_travel(server, index, tmp_path):
    """Dataset 1's walk 002 carries its travel on `joint_Root`, the hips still under it: the tool
    sends that travel on the hips, so the model steps with it. Sent as the file has it, the model
    saw a walk in place and the written file's root joint carried the body over planted feet."""
    from models.eval.metrics import flat_foot_contacts

    clip = next(
        c for c in select(index, dataset="bandai-namco-1", style="normal") if c.name == "dataset-1_walk_normal_002"
    )
    out = tmp_path / "out.bvh"
    assert main(["stylise", str(clip.path), "--url", server, "--style", "elderly", "-o", str(out)]) == 0
    flat, speed = flat_foot_contacts(from_bvh(bvh.read(out)))
    assert flat.sum() >= 5 and np.percentile(speed[flat], 95) < 40.0  # cm/s (read in place: 158)
