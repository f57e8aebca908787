"""LTI rotation prior (`train.style_prior`, models/motion/rotation_ball.py): the ball real data of
a style fills, per joint."""

from __future__ import annotations

import numpy as np
import pytest

from models.eval.plausibility import RotationReference
from models.lti.model import WEIGHTS_DIR, LTIStyleModel
from models.lti.representation import HIPS
from models.motion.rotation_ball import comparable, fit_prior
from models.motion.rotation_ball_kernels import clamp_joint
from models.motion.rotations import quat_angle, quat_mul, yaw_quat
from tests.reference.rotation_ball import clamp_rotations, saturate


@pytest.fixture(scope="module")
def real():
    """Real validation clips of one style (a few thousand frames: quick, and any real data will do)."""
    from models.data import build_index, load_motions, select

    return load_motions(select(build_index(["bandai-namco-2"]), split="val", style="elderly"))


def test_prior_is_the_evaluation_reference(real):
    """Mean and p99 radius per joint are the ones `models.eval.plausibility` scores against (same
    frames): the Hips without its heading, the others as local rotations."""
    mean, radii = fit_prior(np.concatenate([m.rotations for m in real]), inner_q=95.0, outer_q=99.0, margin_deg=0.0)
    ref = RotationReference({"elderly": real})
    assert np.degrees(quat_angle(mean[ref.joint_index], ref.mean["elderly"])).max() < 0.01
    np.testing.assert_allclose(radii[1, ref.joint_index], ref.p99["elderly"], atol=1e-6)
    assert (radii[0] <= radii[1]).all() and np.isinf(radii[:, 0]).all()  # joint_Root: no prior


def test_clamp_keeps_inside_moves_outside_within_outer(real):
    q = np.concatenate([m.rotations for m in real])
    mean, radii = fit_prior(q, 90.0, 99.0, 1.0)
    rng = np.random.default_rng(0)
    # real frames pushed away from the mean by up to 3x their distance: past the prior for many
    rel = quat_mul(mean[None] * np.array([-1, -1, -1, 1.0]), comparable(q[::7]))
    rel = np.where(rel[..., 3:] < 0, -rel, rel)
    scale = rng.uniform(0.5, 3.0, rel.shape[:-1])[..., None]
    half = np.arctan2(np.linalg.norm(rel[..., :3], axis=-1, keepdims=True), rel[..., 3:])
    axis = rel[..., :3] / np.maximum(np.linalg.norm(rel[..., :3], axis=-1, keepdims=True), 1e-12)
    pushed = quat_mul(mean[None], np.concatenate([axis * np.sin(half * scale), np.cos(half * scale)], -1))
    pushed[:, 0] = (0, 0, 0, 1)
    out = clamp_rotations(pushed, mean, radii)
    before, after = quat_angle(comparable(pushed), mean), quat_angle(comparable(out), mean)
    inside = before <= radii[0]
    assert inside.any() and (~inside).any()
    np.testing.assert_array_equal(out[inside], pushed[inside])  # untouched inside the inner radius
    assert (after[:, 1:] <= radii[1, 1:] + 1e-9).all()  # never past the outer radius
    assert (after <= before + 1e-9).all()  # only ever toward the mean
    # the direction away from the mean is kept: the clamped rotation lies on the same geodesic
    moved = ~inside[:, 1:]
    gap = quat_angle(comparable(out), comparable(pushed))[:, 1:][moved]
    np.testing.assert_allclose(gap, (before - after)[:, 1:][moved], atol=1e-6)


def test_saturation_is_continuous_and_monotone():
    d = np.linspace(0.0, 3.0, 3001)
    s = saturate(d, np.array(0.8), np.array(1.0))
    assert (np.diff(s) >= 0).all() and s.max() <= 1.0 and np.abs(np.diff(s)).max() <= np.diff(d).max() + 1e-12
    np.testing.assert_array_equal(s[d <= 0.8], d[d <= 0.8])


def test_hips_prior_ignores_the_heading(real):
    """Turning the character about up turns its clamped Hips the same way."""
    q = np.concatenate([m.rotations for m in real])[::11]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)  # stored in float32: arccos would magnify that
    mean, radii = fit_prior(q, 10.0, 20.0, 0.0)  # tight, so many Hips rotations are clamped
    turn = yaw_quat(np.full(len(q), 1.3))
    turned = q.copy()
    turned[:, HIPS] = quat_mul(turn, q[:, HIPS])
    a, b = clamp_rotations(q, mean, radii), clamp_rotations(turned, mean, radii)
    assert (quat_angle(a[:, HIPS], q[:, HIPS]) > 1e-3).mean() > 0.2
    assert quat_angle(quat_mul(turn, a[:, HIPS]), b[:, HIPS]).max() < 1e-6


def test_compiled_clamp_equals_numpy(real):
    q = np.concatenate([m.rotations for m in real])[::13]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    mean, radii = fit_prior(q, 60.0, 80.0, 0.0)
    want = clamp_rotations(q, mean, radii)
    got = np.array(
        [
            [clamp_joint(tuple(q[f, j]), tuple(mean[j]), radii[0, j], radii[1, j], j == HIPS) for j in range(22)]
            for f in range(len(q))
        ]
    )
    assert quat_angle(got, want).max() < 1e-6  # arccos resolution near 0


def test_committed_weights_carry_a_prior():
    model = LTIStyleModel(weights_dir=WEIGHTS_DIR)
    for style, tr in model.translators.items():
        assert tr.prior_mean is not None and tr.prior_radii is not None, style
        assert np.isfinite(tr.prior_radii[:, 1:]).all() and (tr.prior_radii[0] <= tr.prior_radii[1]).all()
