"""Any humanoid rig: name matching, topology errors, units/axes, and the per-frame mapping on rigs
made from Bandai Namco walks (tests/rigs.py), whose ground truth is the BN walk itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.motion import bvh
from models.motion.humanoid import BN_ROLES, PRESET_NAMES, RigError, humanoid_rig, preset_rig, rig_from_bvh, split_name
from models.motion.humanoid_presets import PRESETS
from models.motion.retarget_stream import FrameRetargeter
from models.motion.skeleton import fk, skeleton_from_bvh

from .clips import angle_deg
from .rigs import SPECS, bn_positions, make_rig

FIXTURES = Path(__file__).parent / "fixtures" / "rigs"
FRAMES = 60


@pytest.mark.parametrize(
    "name, side, base",
    [
        ("mixamorig:LeftUpLeg", "l", "upleg"),
        ("upperarm_twist_01_r", "r", "upperarmtwist01"),
        ("Hand.L", "l", "hand"),
        ("left_knee", "l", "knee"),
        ("Bip01 R Thigh", "r", "thigh"),
        ("J_Bip_L_UpperArm", "l", "upperarm"),
        ("leftUpperArm", "l", "upperarm"),
        ("spine_01", None, "spine01"),
        ("HeadTop_End", None, "headtopend"),
        ("Shoulder_R", "r", "shoulder"),
        ("LHipJoint", "l", "hipjoint"),
    ],
)
def test_split_name(name, side, base):
    assert split_name(name) == (side, base)


def _expected(spec) -> dict[str, str]:
    """role -> joint name of a made rig, from its hand-typed BN renaming."""
    out = {BN_ROLES[b]: n for b, n in spec.rename.items() if b in BN_ROLES}
    out["spine1"] = spec.rename["Spine"]
    inserted_necks = [n for n, parent, child, _ in spec.inserts if child == "Head"]
    if inserted_necks:  # a second neck joint above the first: the upper one is the neck (nearest the head)
        out["neck"] = inserted_necks[-1]
    return out


@pytest.mark.parametrize("name", list(SPECS))
def test_each_fixture_rig_is_matched_by_its_names(name):
    rig = rig_from_bvh((FIXTURES / f"{name}.bvh").read_text())
    mapping = rig.report()["mapping"]
    spec = SPECS[name]
    for role, joint in _expected(spec).items():
        assert mapping[role] == joint, (role, mapping)
    spines = [r for r in ("spine1", "spine2", "spine3", "spine4") if r in mapping]
    assert mapping[spines[-1]] == spec.rename["Chest"]  # the top spine joint is the chest
    inserted = {n for n, *_ in spec.inserts} | {n for n, _ in spec.fingers}
    lower_neck = {spec.rename["Neck"]} if mapping["neck"] != spec.rename["Neck"] else set()
    assert set(rig.unmapped()) <= inserted | lower_neck | {"root"}
    assert {n for n, _ in spec.fingers} <= set(rig.unmapped())


@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_preset_hierarchies_match_their_own_tables(preset):
    rig = preset_rig(preset)
    assert rig.preset is not None
    if preset in PRESETS:
        for role, joint in PRESETS[preset].role_names().items():
            assert rig.joint(role) == joint
        assert rig.up == "y" and rig.units == "cm"


def test_preset_with_a_subset_of_joints_and_a_prefix():
    sk = PRESETS["mixamo"].skeleton()
    body = [n for n in sk.names if "Hand" not in n or n.endswith("Hand")]  # no fingers
    joints = ["mixamorig:" + n for n in reversed(body)]  # any order, with the prefix
    rig = preset_rig("mixamo", joints=joints)
    assert rig.joint("hand_l") == "mixamorig:LeftHand" and len(rig.unmapped()) == 3  # the end-site joints
    with pytest.raises(RigError) as err:
        preset_rig("mixamo", joints=[*joints, "LeftWing"])
    assert err.value.code == "bad_skeleton" and "LeftWing" in err.value.message


def _fixture_skeleton(name: str):
    return skeleton_from_bvh(bvh.read(FIXTURES / f"{name}.bvh"))[0]


def test_partial_rig_names_every_missing_role():
    sk = _fixture_skeleton("mixamo")
    names = tuple(n.replace("Leg", "Stalk").replace("RightHand", "RightPaw") for n in sk.names)
    broken = type(sk)(names, sk.parents, sk.offsets, sk.end_sites)
    with pytest.raises(RigError) as err:
        humanoid_rig(broken)
    assert err.value.code == "missing_roles"
    assert set(err.value.missing) == {"lowerleg_l", "lowerleg_r", "upperleg_l", "upperleg_r", "hand_r"}
    for role in err.value.missing:
        assert role in err.value.message
    # an explicit joint_map completes it
    fixed = humanoid_rig(
        broken,
        joint_map={
            "mixamorig:LeftUpStalk": "upperleg_l",
            "mixamorig:LeftStalk": "lowerleg_l",
            "mixamorig:RightUpStalk": "upperleg_r",
            "mixamorig:RightStalk": "lowerleg_r",
            "mixamorig:RightPaw": "hand_r",
        },
    )
    assert fixed.joint("hand_r") == "mixamorig:RightPaw"


def test_joint_map_overrides_and_bad_maps_are_typed():
    sk = _fixture_skeleton("ue5")
    rig = humanoid_rig(sk, joint_map={"neck_01": "neck", "neck_02": None})
    assert rig.joint("neck") == "neck_01" and "neck_02" in rig.unmapped()
    with pytest.raises(RigError) as err:
        humanoid_rig(sk, joint_map={"hand_l": "hand_l", "wing_l": "hand_l", "foot_l": "tail"})
    assert err.value.code == "bad_joint_map" and "wing_l" in err.value.message and "tail" in err.value.message
    with pytest.raises(RigError) as err:
        humanoid_rig(sk, joint_map={"thigh_twist_01_r": "toes_l"})  # left toes on the right thigh
    assert err.value.code == "bad_topology" and "toes_l (thigh_twist_01_r) is not below foot_l" in err.value.message


def test_headless_or_legless_hierarchy_is_refused():
    text = (
        "HIERARCHY\nROOT Pelvis\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
        " JOINT Knee\n {\n  OFFSET 0 -40 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -40 0\n  }\n }\n}\n"
    )
    with pytest.raises(RigError) as err:
        rig_from_bvh(text)
    assert err.value.code == "missing_roles" and "head" in err.value.missing and "hand_l" in err.value.missing
    with pytest.raises(RigError) as err:
        rig_from_bvh("HIERARCHY\nROOT Hips\n{")
    assert err.value.code == "bad_skeleton"


@pytest.mark.parametrize(
    "name, up, units",
    [("unity", "z", "m"), ("ue5", "z", "cm"), ("mixamo", "y", "cm"), ("smpl", "y", "m"), ("bvh", "y", "m")],
)
def test_units_and_up_are_read_from_the_rig(name, up, units):
    rig = rig_from_bvh((FIXTURES / f"{name}.bvh").read_text())
    assert rig.units == units
    assert rig.up == up
    # BN's zero pose ('bvh' keeps it) says nothing about up: assumed, and reported as such
    assert rig.up_detected == (SPECS[name].rest != "zero")


# --------------------------------------------------------------------------- the mapping, on made rigs


@pytest.fixture(scope="module")
def walk(bn_walk):
    return bn_walk.slice(0, FRAMES)


@pytest.fixture(scope="module")
def bn_mapper(walk):
    return FrameRetargeter(humanoid_rig(walk.skeleton, translated=walk.skeleton.index("Hips")))


def _made(walk, name):
    spec = SPECS[name]
    motion = make_rig(walk, spec)
    hips = motion.skeleton.index(spec.rename["Hips"])
    rig = humanoid_rig(motion.skeleton, up=spec.up, translated=hips)
    return spec, motion, FrameRetargeter(rig)


@pytest.mark.parametrize("name", list(SPECS))
def test_made_rig_maps_as_the_bn_rig_does(walk, bn_mapper, name):
    """Whatever the names, rest pose, extra joints, units and up axis, the BN frame is the one the
    BN walk itself maps to: extra spine and neck joints too (ue5's neck_02, vrm's chest), as the
    trunk maps by length (`retarget_stream.trunk_bones`); the Hips within 0.01 cm: the root rises
    for feet laid by hinge-true limbs, `FrameRetargeter._drop`."""
    spec, motion, fr = _made(walk, name)
    hips, rot = fr.to_model(motion.translations[:, fr.humanoid.translated], motion.rotations)
    ref_hips, ref_rot = bn_mapper.to_model(walk.translations[:, 1], walk.rotations)
    assert fr.scale == pytest.approx(1.0 / spec.unit, rel=1e-6)
    np.testing.assert_allclose(hips, ref_hips, atol=1e-2)
    assert angle_deg(rot, ref_rot).max() < 1e-3  # the BN data are float32-rounded quaternions


@pytest.mark.parametrize("name", list(SPECS))
def test_round_trip_and_a_new_pose_on_made_rigs(walk, bn_mapper, name):
    """to_source(to_model(x), x) == x (intensity 0 gives the input back), unmapped joints exactly as
    sent; a BN pose from 20 frames later lands on the made rig with its mapped joints where BN has
    them, in BN's world (ground truth: the BN walk itself)."""
    spec, motion, fr = _made(walk, name)
    t = fr.humanoid.translated
    root, rot = motion.translations[:, t], motion.rotations
    back_root, back_rot = fr.to_source(*fr.to_model(root, rot), rot)
    np.testing.assert_allclose(back_root, root, atol=1e-9)
    assert angle_deg(back_rot, rot).max() < 1e-4
    unmapped = [motion.skeleton.index(n) for n in fr.humanoid.unmapped()]
    np.testing.assert_array_equal(back_rot[:, unmapped], rot[:, unmapped])

    n = FRAMES - 20
    hips_bn, rot_bn = bn_mapper.to_model(walk.translations[20:, 1], walk.rotations[20:])
    new_root, new_rot = fr.to_source(hips_bn, rot_bn, rot[:n])
    trans = motion.translations[:n].copy()
    trans[:, t] = new_root
    got = (fk(new_rot, trans, motion.skeleton.parents)[1] / spec.unit) @ spec.up_matrix
    sk = walk.skeleton
    bn_trans = np.broadcast_to(sk.offsets, (n, sk.num_joints, 3)).copy()
    bn_trans[:, 1] = hips_bn
    want = fk(rot_bn, bn_trans, sk.parents)[1]
    pairs = [
        (motion.skeleton.index(spec.rename[b]), sk.index(b))
        for b in spec.rename
        if b in BN_ROLES or b in ("Spine", "Chest")
    ]
    if name == "ue5":  # its neck role is the inserted neck_02: compare the others
        pairs = [(a, b) for a, b in pairs if sk.names[b] != "Neck"]
    err = np.linalg.norm(
        (got[:, [a for a, _ in pairs]] - got[:, [0]] * 0 - got[:, [motion.skeleton.index(spec.rename["Hips"])]])
        - (want[:, [b for _, b in pairs]] - want[:, [1]]),
        axis=-1,
    )
    leg = 80.0
    assert np.median(err) / leg < 0.03 and err.max() / leg < 0.06, (np.median(err), err.max())
    # and the hips, so the feet, land where BN's are: the made rig's own floor is BN's floor here
    # (within 0.01 cm: the root rises for feet laid by hinge-true limbs, `FrameRetargeter._drop`)
    np.testing.assert_allclose(got[:, motion.skeleton.index(spec.rename["Hips"])], want[:, 1], atol=1e-2)


def test_made_rig_fixture_motion_positions_are_the_bn_walks(walk):
    """The made rigs are the ground truth only if they move exactly as the BN walk does."""
    pos = walk.global_positions()
    for spec in SPECS.values():
        motion = make_rig(walk, spec)
        got = bn_positions(motion, spec)
        for j, b in enumerate(walk.skeleton.names):
            if spec.rename.get(b, b) is not None:
                np.testing.assert_allclose(got[:, motion.skeleton.index(spec.rename.get(b, b))], pos[:, j], atol=1e-6)
