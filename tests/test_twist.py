"""Swing-twist helpers and `transfer_twist`: a pose keeps its joint positions exactly while its
twists and leaf rotations come from another pose."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from models.motion.rotations import quat_angle, quat_exp, quat_inv, quat_mul, swing_twist, twist_angle
from models.motion.twist import bone_axes, transfer_twist, transfer_twist_t


def _twisted(motion, degrees: float, joints: list[str]):
    """The motion with each listed joint turned about its own bone by `degrees`."""
    sk = motion.skeleton
    axes = bone_axes(sk)
    rot = motion.rotations.copy()
    for name in joints:
        j = sk.index(name)
        rot[:, j] = quat_mul(rot[:, j], quat_exp(np.radians(degrees) * axes[j]))
    return replace(motion, rotations=rot)


def test_swing_twist_splits_a_rotation_into_parts_about_and_across_the_axis():
    rng = np.random.default_rng(0)
    q = quat_exp(rng.normal(size=(200, 3)))
    axis = np.array([0.0, 0.6, 0.8])
    swing, twist = swing_twist(q, axis)
    assert np.allclose(np.abs(np.sum(quat_mul(swing, twist) * q, -1)), 1.0)
    assert np.allclose(np.cross(twist[:, :3], axis), 0.0, atol=1e-9)  # twist turns about the axis
    assert np.allclose(swing[:, :3] @ axis, 0.0, atol=1e-9)  # swing turns across it
    turn = quat_exp(0.7 * axis)
    assert np.allclose(twist_angle(turn, axis), 0.7)


def test_transfer_twist_keeps_positions_and_takes_the_sources_twists(bn_walk):
    walk = bn_walk.slice(0, 40)
    wrung = _twisted(walk, 120.0, ["Neck", "Head", "Hand_L", "LowerArm_R", "Foot_L", "Toes_R", "Spine"])
    fixed = replace(wrung, rotations=transfer_twist(walk.skeleton, walk.rotations, wrung.rotations))
    assert np.abs(fixed.global_positions() - wrung.global_positions()).max() < 1e-4  # cm
    # every twisted joint is back where the source has it
    for name in ("Neck", "Head", "Hand_L", "LowerArm_R", "Foot_L", "Toes_R", "Spine"):
        j = walk.skeleton.index(name)
        assert np.degrees(quat_angle(fixed.rotations[:, j], walk.rotations[:, j])).max() < 0.1, name
    # the spine's twist turns the shoulders: the chest, fixed by its children, takes it over
    chest = walk.skeleton.index("Chest")
    world_fixed, world_wrung = fixed.global_transforms()[0], wrung.global_transforms()[0]
    assert np.degrees(quat_angle(world_fixed[:, chest], world_wrung[:, chest])).max() < 0.1


def test_transfer_twist_is_the_identity_on_the_source_itself(bn_walk):
    walk = bn_walk.slice(0, 20)
    same = transfer_twist(walk.skeleton, walk.rotations, walk.rotations)
    assert np.degrees(quat_angle(same, walk.rotations)).max() < 0.1  # float32 clips: arccos near 1


def test_torch_twin_matches_numpy(bn_walk):
    walk = bn_walk.slice(0, 10)
    wrung = _twisted(walk, 70.0, ["Head", "Hand_R", "LowerLeg_L"])
    want = transfer_twist(walk.skeleton, walk.rotations, wrung.rotations)
    got = transfer_twist_t(walk.skeleton, torch.as_tensor(walk.rotations), torch.as_tensor(wrung.rotations)).numpy()
    assert np.degrees(quat_angle(got, want)).max() < 1e-4


def test_kept_joints_keep_the_poses_own_rotation(bn_walk):
    walk = bn_walk.slice(0, 20)
    wrung = _twisted(walk, 90.0, ["Hand_L", "UpperLeg_R", "Spine"])
    out = transfer_twist(walk.skeleton, walk.rotations, wrung.rotations, keep=("Hand_L", "UpperLeg_R"))
    for name, want in (("Hand_L", wrung), ("UpperLeg_R", wrung), ("Spine", walk)):
        j = walk.skeleton.index(name)
        assert np.degrees(quat_angle(out[:, j], want.rotations[:, j])).max() < 0.1, name
    assert np.abs(replace(walk, rotations=out).global_positions() - wrung.global_positions()).max() < 1e-4


def test_lpn_keeps_the_spine_untwisted(index):
    """LPN-FiLM toward `exhausted` turned the spine ~176 degrees about itself (and the chest back):
    invisible in joint positions, a wrung body on a skinned character."""
    from models.data import load_motion, select
    from models.interface import FrameBatch
    from models.lpn import load as load_lpn
    from models.settings import get_settings

    model = load_lpn(get_settings().weights_dir / "lpn")
    walk = load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])
    weights = np.zeros((1, len(model.styles())))
    weights[0, model.styles().index("exhausted")] = 1.0
    state, spine = model.init_state(1), walk.skeleton.index("Spine")
    axis = bone_axes(walk.skeleton)[spine]
    for t in range(60):
        out, state = model.step_batch(
            state, FrameBatch(walk.translations[t : t + 1, 1], walk.rotations[t : t + 1]), weights
        )
        twist = np.degrees(twist_angle(quat_mul(quat_inv(walk.rotations[t, spine]), out.rotations[0, spine]), axis))
        assert abs(twist) < 45.0, (t, twist)


def test_compiled_equals_numpy_reference(bn_walk):
    from tests.reference.twist import transfer_twist_numpy

    walk = bn_walk.slice(0, 30)
    wrung = _twisted(walk, 100.0, ["Head", "Hand_R", "LowerLeg_L", "Spine", "Foot_R"])
    for keep in ((), ("Hand_R", "UpperLeg_L")):
        want = transfer_twist_numpy(walk.skeleton, walk.rotations, wrung.rotations, keep)
        got = transfer_twist(walk.skeleton, walk.rotations, wrung.rotations, keep)
        assert np.degrees(quat_angle(got, want)).max() < 1e-4  # arccos near 1: ~1e-5 deg of round-off
    # broadcasting one source pose over a batch, as LPN-FiLM does
    got = transfer_twist(walk.skeleton, walk.rotations[0], wrung.rotations)
    want = transfer_twist_numpy(
        walk.skeleton, np.broadcast_to(walk.rotations[0], wrung.rotations.shape), wrung.rotations
    )
    assert got.shape == wrung.rotations.shape and np.degrees(quat_angle(got, want)).max() < 1e-4


def test_split_evenly_keeps_the_chain_and_shares_its_turn():
    """The composite parent * child is kept; the parent takes half the chain's turn from rest,
    so a spine flipped 180 degrees about itself with the chest flipped back is split as no turn."""
    from models.motion.twist import split_evenly

    rng = np.random.default_rng(1)
    rest_p, rest_c = quat_exp(rng.normal(0, 0.5, (2, 3)))
    p, c = quat_exp(rng.normal(0, 0.8, (2, 50, 3)))
    new_p, new_c = split_evenly(p, c, rest_p, rest_c)
    assert quat_angle(quat_mul(new_p, new_c), quat_mul(p, c)).max() < 1e-6  # quat_angle resolves ~3e-8
    turn = quat_angle(quat_mul(p, c), quat_mul(rest_p, rest_c))
    np.testing.assert_allclose(quat_angle(new_p, np.broadcast_to(rest_p, new_p.shape)), turn / 2, atol=1e-6)
    flip = quat_exp(np.array([np.pi, 0.0, 0.0]))
    flipped_p, flipped_c = quat_mul(rest_p, flip), quat_mul(quat_inv(flip), rest_c)
    back_p, back_c = split_evenly(flipped_p, flipped_c, rest_p, rest_c)
    assert quat_angle(back_p, rest_p) < 1e-6 and quat_angle(back_c, rest_c) < 1e-6
