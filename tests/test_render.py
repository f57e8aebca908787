"""The matplotlib renderer writes real, non-blank images for BN and CMU skeletons, and its oriented
solids (head, hands, feet) follow the joints' world rotations, calibrated per skeleton."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from PIL import Image

from models.motion.assets import bandai_namco_pose, cmu_pose
from models.motion.features import facing_yaw
from models.motion.orientation import FACES, face_normals, find_parts, reference_rig, rig, solid_corners
from models.motion.render import joint_sides, render_contact_sheet, render_gif, up_axis, upright
from models.motion.resample import resample
from models.motion.rotations import quat_exp, quat_mul, quat_to_matrix
from models.motion.skeleton import Motion
from tests.rigs import EXTRA_SPECS, SPECS, bn_positions, make_rig


def part_frames(global_rotations: np.ndarray, joint: int, axes: np.ndarray) -> np.ndarray:
    """(..., 3, 3) world axes (columns x, y, z) of a part from world joint rotations (..., J, 4)."""
    return quat_to_matrix(global_rotations[..., joint, :]) @ axes


def world_axes(motion: Motion) -> dict[str, np.ndarray]:
    """Per part (`head`, `hand_l`, `foot_r`, ...), its world axes over the motion (F, 3, 3):
    column 0 is where the face looks / the fingers point / the toes point, column 1 up / the thumb."""
    g_rot, _ = motion.global_transforms()
    return {s.part: part_frames(g_rot, s.joint, s.axes) for s in rig(motion) if not s.mark}


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
    path = render_contact_sheet(
        [bn_walk.slice(0, 30), resample(cmu_walk.slice(0, 120), 30)],
        tmp_path / "sheet.png",
        frames=3,
        titles=["bn", "cmu"],
        panel_size=1.5,
        dpi=50,
    )
    with Image.open(path) as img:
        assert img.format == "PNG" and img.size[0] > 100 and img.size[1] > 100
        _not_blank(img)
    single = render_contact_sheet(bn_walk, tmp_path / "one.png", frames=4, columns=2, panel_size=1.2, dpi=50)
    with Image.open(single) as img:
        assert img.size[1] > img.size[0] * 0.8  # 2 x 2 grid
        _not_blank(img)


def test_gif_is_animated(tmp_path, bn_walk, cmu_walk):
    path = render_gif(
        [bn_walk.slice(0, 30), cmu_walk.slice(0, 120)],
        tmp_path / "walk.gif",
        fps=6,
        seconds=1.0,
        titles=["bn", "cmu"],
        panel_size=1.5,
        dpi=50,
    )
    with Image.open(path) as img:
        assert img.format == "GIF" and img.n_frames >= 5  # 1 s at 6 fps (Pillow may merge equal frames)
        img.seek(3)
        _not_blank(img)


# --------------------------------------------------------------------------- oriented solids


def _turn(motion: Motion, joint: str, degrees: float) -> Motion:
    """A copy with `joint` turned about its own bone (the offset from its parent): moves no joint."""
    sk = motion.skeleton
    j = sk.index(joint)
    q = quat_exp(sk.offsets[j] / np.linalg.norm(sk.offsets[j]) * np.radians(degrees))
    rotations = motion.rotations.copy()
    rotations[:, j] = quat_mul(q, rotations[:, j])
    return replace(motion, rotations=rotations)


def _body_forward(motion: Motion) -> np.ndarray:
    yaw = facing_yaw(motion.global_positions(), motion.skeleton)
    return np.stack([np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)], axis=-1)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def test_parts_are_found_by_name(bn_walk, cmu_walk):
    assert {p: bn_walk.skeleton.names[j] for p, j in find_parts(bn_walk.skeleton).items()} == {
        "head": "Head",
        "hand_l": "Hand_L",
        "hand_r": "Hand_R",
        "foot_l": "Foot_L",
        "foot_r": "Foot_R",
        "toe_l": "Toes_L",
        "toe_r": "Toes_R",
    }
    parts = {p: cmu_walk.skeleton.names[j] for p, j in find_parts(cmu_walk.skeleton).items()}
    assert parts["head"] == "Head" and parts["hand_l"] == "LeftHand" and parts["hand_r"] == "RightHand"
    assert parts["foot_l"] == "LeftFoot" and parts["toe_r"] == "RightToeBase"
    # calibrated on the committed reference poses: Xia's CMU variant (other finger names) borrows the CMU one
    assert reference_rig(bn_walk.skeleton) == "bandai_namco" and reference_rig(cmu_walk.skeleton) == "cmu"
    assert reference_rig(cmu_walk.skeleton) != reference_rig(bn_walk.skeleton)


def test_reference_pose_axes_face_the_body_facing():
    """On the BN asset pose the head looks where the body faces, the thumbs point forward and the
    feet point forward, level; on the CMU asset (a T-pose) the palms face down."""
    for pose in (bandai_namco_pose(), cmu_pose()):
        axes = {p: a[0] for p, a in world_axes(pose).items()}
        forward = _body_forward(pose)[0]
        assert _dot(axes["head"][:, 0], forward) > 0.999 and axes["head"][1, 1] > 0.999
        for tag in ("l", "r"):
            assert _dot(axes[f"hand_{tag}"][:, 1], forward) > 0.5  # thumb forward
            assert _dot(axes[f"foot_{tag}"][:, 0], forward) > 0.8 and axes[f"foot_{tag}"][1, 1] > 0.999
    cmu = world_axes(cmu_pose())
    assert cmu["hand_l"][0, 1, 2] < -0.95 and cmu["hand_r"][0, 1, 2] > 0.95  # z: left palm normal, right back


def test_walk_axes_follow_the_body(bn_walk, cmu_walk):
    """Calibrated on the skeleton's reference pose, a real walk's head looks ahead and its toes
    point ahead, frame after frame (the BN zero pose, lying along X, would give nonsense)."""
    for motion in (bn_walk, cmu_walk):
        axes, forward = world_axes(motion), _body_forward(motion)
        assert np.mean(_dot(axes["head"][:, :, 0], forward)) > 0.9
        for tag in "lr":
            assert np.mean(_dot(axes[f"foot_{tag}"][:, :, 0], forward)) > 0.8
            assert np.mean(_dot(axes[f"hand_{tag}"][:, :, 1], forward)) > 0.4


def test_head_turned_about_its_bone_flips_the_nose(bn_walk):
    walk = bn_walk.slice(0, 60)
    turned = _turn(walk, "Head", 180.0)
    assert np.allclose(turned.global_positions(), walk.global_positions())  # invisible to a stick figure
    before, after = world_axes(walk)["head"][:, :, 0], world_axes(turned)["head"][:, :, 0]
    assert np.all(_dot(before, after) < -0.8)
    assert np.all(_dot(after, _body_forward(walk)) < -0.5)  # looking backwards from frame 0: calibrated per skeleton
    assert np.all(_dot(world_axes(_turn(walk, "Head", 120.0))["head"][:, :, 0], before) < -0.2)


def test_wrist_twist_flips_the_thumb(bn_walk, cmu_walk):
    for motion, hand in ((bn_walk.slice(0, 60), "Hand_L"), (cmu_walk.slice(0, 240), "RightHand")):
        twisted = _turn(motion, hand, 180.0)
        wrist = motion.skeleton.index(hand)
        arm = [j for j in range(motion.skeleton.num_joints) if j <= wrist]  # up to the wrist (Xia has finger joints)
        assert np.allclose(twisted.global_positions()[:, arm], motion.global_positions()[:, arm], atol=1e-6)
        part = "hand_l" if hand == "Hand_L" else "hand_r"
        before, after = world_axes(motion)[part], world_axes(twisted)[part]
        assert np.all(_dot(before[:, :, 1], after[:, :, 1]) < -0.9)  # the thumb swaps sides
        assert np.all(_dot(before[:, :, 0], after[:, :, 0]) > 0.9)  # the hand still points along the forearm


def test_unknown_skeleton_is_calibrated_on_its_first_frame(bn_walk):
    sk = bn_walk.skeleton
    renamed = replace(bn_walk, skeleton=replace(sk, names=("Root",) + sk.names[1:])).slice(30, 60)
    assert reference_rig(renamed.skeleton) is None
    head = world_axes(renamed)["head"]
    assert _dot(head[0, :, 0], _body_forward(renamed)[0]) > 0.999


def test_solids_sit_on_the_body():
    """BN asset pose: the soles reach the floor, the head tops the body at a person's height, the
    nose sticks out in front and every face normal points out of its block."""
    pose = bandai_namco_pose()
    solids = rig(pose)
    rot, pos = pose.global_transforms()
    corners = solid_corners(rot[0], pos[0], solids)
    part = {s.part: i for i, s in enumerate(solids)}
    forward = _body_forward(pose)[0]
    assert abs(corners[[part["foot_l"], part["foot_r"]], :, 1].min()) < 4.0  # cm
    assert 150 < corners[part["head"], :, 1].max() < 175
    assert (corners[part["nose"]] @ forward).max() > (corners[part["head"]] @ forward).max() + 5.0
    centre_out = corners[:, FACES].mean(axis=2) - corners.mean(axis=1, keepdims=True)
    assert np.all(_dot(face_normals(corners), centre_out) > 0)
    assert all(np.allclose(s.axes.T @ s.axes, np.eye(3)) and np.linalg.det(s.axes) > 0.999 for s in solids)


def test_other_humanoid_rigs_get_solids_from_their_first_frame(tmp_path, bn_walk):
    """Mixamo / SMPL / VRM rigs made from the BN walk (other names, T-pose rests, metres): parts
    and sides come from `humanoid` roles, the calibration from the clip's first frame, and the
    head and feet then point where the BN walk's do."""
    walk = bn_walk.slice(0, 60)
    bn = world_axes(walk)
    for name in ("mixamo", "smpl", "vrm"):
        made = make_rig(walk, SPECS[name])
        assert reference_rig(made.skeleton) is None
        parts = find_parts(made.skeleton)
        assert set(parts) == {"head", "hand_l", "hand_r", "foot_l", "foot_r", "toe_l", "toe_r"}
        sides = joint_sides(made.skeleton)  # 8 limb joints a side (the made fingers are lopsided)
        assert (sides == 1).sum() >= 8 and (sides == -1).sum() >= 8 and sides[parts["head"]] == 0
        assert all(sides[j] == (1 if p.endswith("_l") else -1) for p, j in parts.items() if p != "head")
        axes = world_axes(made)
        assert np.mean(_dot(axes["head"][:, :, 0], bn["head"][:, :, 0])) > 0.9, name
        for part in ("foot_l", "foot_r"):
            assert np.mean(_dot(axes[part][:, :, 0], bn[part][:, :, 0])) > 0.8, (name, part)
    path = render_contact_sheet(
        make_rig(walk, SPECS["mixamo"]), tmp_path / "mixamo.png", frames=2, panel_size=1.5, dpi=50
    )
    with Image.open(path) as img:
        _not_blank(img)  # red and blue limbs: sides from the `mixamorig:Left…` names


def test_z_up_rigs_are_drawn_standing(tmp_path, bn_walk):
    """Rigs made Z up (Unreal, Blender, an Xsens-style capture export; cm or m, A-pose, T-pose or
    first-frame rest) are drawn in their own up axis: `upright` puts every joint where the Y-up BN
    walk has it (cm), and the head and feet then face where the BN walk's do."""
    walk = bn_walk.slice(0, 60)
    bn = world_axes(walk)
    assert up_axis(walk) == "y" and upright(walk) is walk
    for spec in (SPECS["ue5"], SPECS["blender"], EXTRA_SPECS["xsens"]):
        made = make_rig(walk, spec)
        assert up_axis(made) == "z", spec.name
        standing = upright(made)
        np.testing.assert_allclose(standing.global_positions(), bn_positions(made, spec), atol=1e-6)
        axes = world_axes(standing)
        assert np.mean(_dot(axes["head"][:, :, 0], bn["head"][:, :, 0])) > 0.9, spec.name
        for part in ("foot_l", "foot_r"):
            assert np.mean(_dot(axes[part][:, :, 0], bn[part][:, :, 0])) > 0.8, (spec.name, part)
    path = render_contact_sheet(
        make_rig(walk, EXTRA_SPECS["xsens"]), tmp_path / "xsens.png", frames=2, panel_size=1.5, dpi=50
    )
    with Image.open(path) as img:
        _not_blank(img)
