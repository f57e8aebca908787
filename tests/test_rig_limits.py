"""Every invalid rig is a typed error, found before anything costly is built from it
(`service.rig_check`), and rigs are cached by what they are, not how their header is spelled
(`service.skeletons`). No server: `adapter_for` is what a session's `start`, a crowd's `join`
and `POST /v1/skeletons` all go through."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from models.motion.assets import bandai_namco_skeleton
from service import rig_check, skeletons
from service.protocol import ProtocolError
from service.skeletons import adapter_for

FIXTURES = Path(__file__).parent / "fixtures" / "rigs"
BN = bandai_namco_skeleton()


@pytest.fixture(scope="module")
def mixamo() -> str:
    return (FIXTURES / "mixamo.bvh").read_text().split("MOTION")[0] + "MOTION\n"


def chain(depth: int, fan: int = 0) -> str:
    """A hierarchy `depth` joints deep (plus `fan` leaves under the root)."""
    head = "HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\nCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
    leaves = "".join(
        f"JOINT leaf{i}\n{{\nOFFSET 1 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n}}\n" for i in range(fan)
    )
    links = "".join(
        f"JOINT j{i}\n{{\nOFFSET 0 1 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n" for i in range(depth - 1)
    )
    return head + leaves + links + "}\n" * depth + "MOTION\n"


def compact_chain(depth: int) -> str:
    """A chain `depth` joints deep in as few bytes as BVH allows (under the header cap)."""
    return "ROOT a\n{\nOFFSET 0 0 0\n" + "JOINT a\n{\nOFFSET 0 1 0\n" * (depth - 1) + "}\n" * depth + "MOTION\n"


def with_offsets(text: str, joint_pattern: str, offset: str) -> str:
    """`text` with the OFFSET of every joint whose name matches set to `offset`."""
    out, current = [], None
    for line in text.splitlines():
        named = re.match(r"\s*(?:ROOT|JOINT)\s+(\S+)", line)
        if named:
            current = named.group(1)
        elif line.strip().startswith("End Site"):
            current = None
        if line.strip().startswith("OFFSET") and current and re.search(joint_pattern, current):
            line = f"OFFSET {offset}"
        out.append(line)
    return "\n".join(out) + "\n"


def refused(header: str) -> ProtocolError:
    with pytest.raises(ProtocolError) as caught:
        adapter_for(None, header, BN)
    assert caught.value.fatal
    return caught.value


@pytest.mark.parametrize(
    ("edit", "code", "kind"),
    [
        (lambda t: with_offsets(t, r"Spine$", "1e308 0 0"), "bad_skeleton", "bad_offset"),
        (lambda t: with_offsets(t, r"Spine1$", "0 -2e5 0"), "bad_skeleton", "bad_offset"),
        (lambda t: with_offsets(t, r"(Leg|Foot)$", "0 0 0"), "unsupported_skeleton", "bad_topology"),
        (lambda t: with_offsets(t, r"ForeArm$", "0 0 0"), "unsupported_skeleton", "bad_topology"),
        (lambda t: t.replace("mixamorig:Hips", "H" * 1_000_000, 1), "bad_skeleton", "rig_too_large"),
        (lambda t: t.replace("mixamorig:Hips", "H" * 300, 1), "bad_skeleton", "bad_joint_name"),
        (lambda t: t.replace("mixamorig:Spine\n", "mixamorig:Sp\x07ine\n", 1), "bad_skeleton", "bad_joint_name"),
        (lambda t: t.replace("mixamorig:Head\n", "mixamorig:Head\u200b\n", 1), "bad_skeleton", "bad_joint_name"),
        (lambda t: chain(5_000), "bad_skeleton", "rig_too_large"),
        (lambda t: compact_chain(5_000), "bad_skeleton", "too_many_joints"),
        (lambda t: chain(10, fan=600), "bad_skeleton", "too_many_joints"),
        (lambda t: chain(100), "bad_skeleton", "rig_too_deep"),
    ],
    ids=[
        "offset-1e308",
        "offset-huge",
        "zero-legs",
        "zero-forearms",
        "header-1MB",
        "name-long",
        "name-bell",
        "name-zero-width",
        "depth-5000",
        "depth-5000-compact",
        "joints-600",
        "depth-100",
    ],
)
def test_each_bad_rig_is_refused_with_its_own_kind_before_the_build(mixamo, edit, code, kind, monkeypatch):
    def build(*_args, **_kwargs):
        raise AssertionError("a retargeter was built for a rig the checks should have refused")

    monkeypatch.setattr(skeletons, "Retarget", build)
    err = refused(edit(mixamo))
    assert (err.code, err.message.split(":", 1)[0]) == (code, kind), err.message


def test_the_limits_let_every_shipped_rig_through(mixamo):
    for path in sorted(FIXTURES.glob("*.bvh")):
        assert adapter_for(None, path.read_text(), BN).num_joints > 20, path.name
    for preset in ("cmu", "mixamo", "smpl"):
        assert adapter_for(preset, None, BN).report()["retargeted"]
    at_limit = chain(rig_check.MAX_DEPTH)
    with pytest.raises(ProtocolError) as caught:  # deep enough is accepted by the limits; it is just no humanoid
        adapter_for(None, at_limit, BN)
    assert caught.value.code == "unsupported_skeleton"


def test_a_preset_joint_list_with_a_bad_name_is_refused():
    with pytest.raises(ProtocolError) as caught:
        adapter_for("mixamo", None, BN, joints=["Hips", "x" * 1_000])
    assert caught.value.message.startswith("bad_joint_name")


def test_one_rig_spelled_two_ways_is_built_once(mixamo):
    """The cache keys on the rig (names, hierarchy, offsets), not its text: the same rig with
    other spacing and number formatting gives the very same adapter."""
    respelled = re.sub(
        r"OFFSET\s+(\S+)\s+(\S+)\s+(\S+)",
        lambda m: "OFFSET  " + "\t".join(f"{float(v):.9e}" for v in m.groups()),
        mixamo,
    ).replace("\n", "\r\n")
    assert respelled != mixamo
    assert adapter_for(None, respelled, BN) is adapter_for(None, mixamo, BN)
    moved = with_offsets(mixamo, r"Spine$", "0 11 0")  # another rig: another adapter
    assert adapter_for(None, moved, BN) is not adapter_for(None, mixamo, BN)
