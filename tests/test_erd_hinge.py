"""Hinge-aware twist transfer (`models.motion.hinge`): elbows and knees fitted from real
rotations; the parent's twist that lays the child's bone in its hinge plane moves no joint."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from models.motion.hinge import Hinges, fit_hinges
from models.motion.rotations import quat_angle, quat_apply, quat_exp, quat_inv, quat_mul, twist_angle
from models.motion.twist import bone_axes, transfer_twist, transfer_twist_t

HINGED = ("LowerArm_L", "LowerArm_R", "LowerLeg_L", "LowerLeg_R")


def _hinges(walk, limited: bool = False) -> Hinges:
    """Fitted on one walk; without `limited`, the parents' twist left free (one walk's twist
    interval is a few degrees wide)."""
    hinges = fit_hinges(walk.skeleton, walk.rotations)
    return hinges if limited else replace(hinges, lo=np.full_like(hinges.lo, -np.pi), hi=np.full_like(hinges.hi, np.pi))


def _swung_sideways(motion, degrees: float):
    """The motion with each elbow and knee swung off its hinge: about the axis square to both its
    bone and the hinge axis (the bone leaves the hinge plane)."""
    sk, hinges = motion.skeleton, _hinges(motion)
    axes = bone_axes(sk)
    rot = motion.rotations.copy()
    for k, j in enumerate(hinges.joints):
        across = np.cross(axes[j], hinges.axes[k])
        rot[:, j] = quat_mul(quat_exp(np.radians(degrees) * across)[None], rot[:, j])
    return replace(motion, rotations=rot)


def test_the_fit_finds_elbows_and_knees_and_real_bends_are_positive(bn_walk):
    hinges = _hinges(bn_walk, limited=True)
    assert sorted(bn_walk.skeleton.names[j] for j in hinges.joints) == sorted(HINGED)
    assert np.degrees(off_hinge(bn_walk.skeleton, hinges, bn_walk.rotations)).max() < 1.0  # real joints are hinges
    assert np.all(hinges.lo < 0) and np.all(hinges.hi > 0)


def test_hinge_transfer_keeps_positions_and_puts_the_child_back_on_its_hinge(bn_walk):
    walk = bn_walk.slice(0, 60)
    swung = _swung_sideways(walk, 25.0)
    hinges = _hinges(bn_walk)
    sk = walk.skeleton
    plain = transfer_twist(sk, walk.rotations, swung.rotations)
    hinged = transfer_twist(sk, walk.rotations, swung.rotations, hinges=hinges)
    for out in (plain, hinged):
        assert np.abs(replace(walk, rotations=out).global_positions() - swung.global_positions()).max() < 1e-4
    bent = _bend(sk, hinges, swung.rotations) > hinges.fade  # where the turn is not faded
    assert bent.mean() > 0.2
    assert np.degrees(off_hinge(sk, hinges, plain)[bent]).max() > 15.0  # the input's twist leaves it off
    assert np.degrees(off_hinge(sk, hinges, hinged)[bent]).max() < 0.5
    # the hinge joint turns back about its own bone, so the hands and feet face nearer where
    # the plain transfer has them than with the parent's turn alone
    lo, hi = hinges.lo.copy(), hinges.hi.copy()
    lo[:, 1], hi[:, 1] = np.pi, -np.pi  # an empty interval: no turn back
    alone = transfer_twist(sk, walk.rotations, swung.rotations, hinges=replace(hinges, lo=lo, hi=hi))
    world = {
        k: replace(walk, rotations=r).global_transforms()[0]
        for k, r in (("plain", plain), ("hinged", hinged), ("alone", alone))
    }
    ends = [sk.index(n) for n in ("Hand_L", "Hand_R", "Foot_L", "Foot_R")]
    turned = quat_angle(world["hinged"][:, ends], world["plain"][:, ends]).mean()
    assert turned < 0.5 * quat_angle(world["alone"][:, ends], world["plain"][:, ends]).mean()


def test_the_parents_twist_stays_in_its_real_interval(bn_walk):
    walk = bn_walk.slice(0, 60)
    swung = _swung_sideways(walk, 25.0)
    hinges = _hinges(bn_walk, limited=True)
    sk = walk.skeleton
    out = transfer_twist(sk, walk.rotations, swung.rotations, hinges=hinges)
    assert np.abs(replace(walk, rotations=out).global_positions() - swung.global_positions()).max() < 1e-4
    parents = sk.parents[hinges.joints]
    axes, mean = bone_axes(sk)[parents], hinges.mean[:, 0]
    twist = twist_angle(quat_mul(quat_inv(mean)[None], out[:, parents]), axes)
    before = twist_angle(quat_mul(quat_inv(mean)[None], walk.rotations[:, parents]), axes)
    lo, hi = np.minimum(hinges.lo[:, 0], before), np.maximum(hinges.hi[:, 0], before)
    assert np.all((twist >= lo - 1e-6) & (twist <= hi + 1e-6))
    assert np.mean(np.isclose(twist, lo) | np.isclose(twist, hi)) > 0.3  # the limit is what held it


def test_a_real_pose_is_left_as_it_is(bn_walk):
    walk = bn_walk.slice(0, 40)
    out = transfer_twist(walk.skeleton, walk.rotations, walk.rotations, hinges=_hinges(bn_walk))
    assert np.abs(np.abs(np.sum(out * walk.rotations, -1)) - 1.0).max() < 1e-5


def test_torch_twin_matches_the_kernel_with_hinges(bn_walk):
    walk = bn_walk.slice(0, 20)
    swung = _swung_sideways(walk, 30.0)
    hinges = _hinges(bn_walk)
    want = transfer_twist(walk.skeleton, walk.rotations, swung.rotations, hinges=hinges)
    got = transfer_twist_t(
        walk.skeleton, torch.as_tensor(walk.rotations), torch.as_tensor(swung.rotations), hinges=hinges
    ).numpy()
    assert np.abs(np.abs(np.sum(got * want, -1)) - 1.0).max() < 1e-9


def test_saved_hinges_load_the_same(bn_walk, tmp_path):
    hinges = _hinges(bn_walk)
    back = Hinges.load(hinges.save(tmp_path / "hinges.npz"))
    for key in ("joints", "axes", "bend", "mean", "lo", "hi"):
        assert np.array_equal(getattr(back, key), getattr(hinges, key)), key
    assert back.fade == hinges.fade


def off_hinge(sk, hinges: Hinges, rotations: np.ndarray) -> np.ndarray:
    """(T, K) angle (radians) by which each hinge joint's bone leaves its hinge plane."""
    axes = bone_axes(sk)[hinges.joints]
    q = rotations[:, hinges.joints]
    d = quat_apply(q, np.broadcast_to(axes, q.shape[:-1] + (3,)))
    return np.arcsin(np.clip(np.abs(np.sum(d * hinges.axes, -1)), 0.0, 1.0))


def _bend(sk, hinges: Hinges, rotations: np.ndarray) -> np.ndarray:
    """(T, K) the angle between each hinge joint's bone and its parent's (radians)."""
    axes = bone_axes(sk)
    q = rotations[:, hinges.joints]
    d = quat_apply(q, np.broadcast_to(axes[hinges.joints], q.shape[:-1] + (3,)))
    parent_axes = axes[sk.parents[hinges.joints]]
    return np.arccos(np.clip(np.sum(d * parent_axes, -1), -1.0, 1.0))
