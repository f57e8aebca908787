import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from models.motion import rotations as R
from models.motion import rotations_torch as RT

rng = np.random.default_rng(0)
QUATS = Rotation.random(500, random_state=1).as_quat()


@pytest.mark.parametrize("order", ["ZXY", "ZYX", "XYZ", "YXZ"])
def test_euler_round_trip_and_torch_matches_scipy(order):
    angles = rng.uniform(-170, 170, size=(200, 3))
    angles[:, 1] = rng.uniform(-85, 85, size=200)  # away from gimbal lock for a unique inverse
    q = R.euler_to_quat(angles, order)
    np.testing.assert_allclose(R.quat_to_euler(q, order), angles, atol=1e-8)
    mt = RT.euler_to_matrix_t(torch.tensor(angles), order).numpy()
    np.testing.assert_allclose(mt, R.quat_to_matrix(q), atol=1e-10)


def test_bvh_order_is_intrinsic():
    """Channels "Zrotation Xrotation Yrotation" mean R = Rz @ Rx @ Ry."""
    z, x, y = 30.0, 40.0, 50.0
    expected = (
        Rotation.from_euler("z", z, degrees=True)
        * Rotation.from_euler("x", x, degrees=True)
        * Rotation.from_euler("y", y, degrees=True)
    ).as_matrix()
    np.testing.assert_allclose(R.quat_to_matrix(R.euler_to_quat(np.array([z, x, y]), "ZXY")), expected, atol=1e-12)


def test_torch_quaternion_functions_match_scipy():
    qt = torch.tensor(QUATS)
    np.testing.assert_allclose(RT.quat_to_matrix_t(qt).numpy(), Rotation.from_quat(QUATS).as_matrix(), atol=1e-12)
    back = RT.matrix_to_quat_t(RT.quat_to_matrix_t(qt)).numpy()
    np.testing.assert_allclose(np.abs((back * QUATS).sum(-1)), 1.0, atol=1e-10)
    other = Rotation.random(500, random_state=2).as_quat()
    np.testing.assert_allclose(
        R.quat_to_matrix(RT.quat_mul_t(qt, torch.tensor(other)).numpy()),
        (Rotation.from_quat(QUATS) * Rotation.from_quat(other)).as_matrix(),
        atol=1e-12,
    )
    np.testing.assert_allclose(
        R.quat_to_matrix(R.quat_mul(QUATS, other)),
        (Rotation.from_quat(QUATS) * Rotation.from_quat(other)).as_matrix(),
        atol=1e-12,
    )
    v = rng.normal(size=(500, 3))
    np.testing.assert_allclose(
        RT.quat_apply_t(qt, torch.tensor(v)).numpy(), Rotation.from_quat(QUATS).apply(v), atol=1e-12
    )
    np.testing.assert_allclose(R.quat_apply(QUATS, v), Rotation.from_quat(QUATS).apply(v), atol=1e-12)


def test_expmap_and_6d_match_scipy_including_zero_angle():
    rotvec = Rotation.from_quat(QUATS).as_rotvec()
    rotvec[0] = 0.0
    rotvec[1] = 1e-7
    q = RT.expmap_to_quat_t(torch.tensor(rotvec)).numpy()
    np.testing.assert_allclose(R.quat_to_matrix(q), Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(RT.quat_to_expmap_t(torch.tensor(q)).numpy(), rotvec, atol=1e-9)
    np.testing.assert_allclose(R.quat_log(R.quat_exp(rotvec)), rotvec, atol=1e-9)
    mats = Rotation.from_quat(QUATS).as_matrix()
    np.testing.assert_allclose(R.sixd_to_matrix(R.matrix_to_6d(mats)), mats, atol=1e-12)
    noisy = R.matrix_to_6d(mats) + rng.normal(scale=1e-3, size=(500, 6))
    ortho = R.sixd_to_matrix(noisy)
    np.testing.assert_allclose(ortho @ np.swapaxes(ortho, -1, -2), np.broadcast_to(np.eye(3), ortho.shape), atol=1e-12)


def test_six_d_to_matrix_agrees_with_its_torch_twin():
    noisy = R.matrix_to_6d(Rotation.from_quat(QUATS).as_matrix()) + np.random.default_rng(3).normal(
        scale=0.1, size=(500, 6)
    )
    np.testing.assert_allclose(R.sixd_to_matrix(noisy), RT.sixd_to_matrix_t(torch.tensor(noisy)).numpy(), atol=1e-12)


def test_torch_expmap_gradient_is_finite_at_zero():
    r = torch.zeros(4, 3, requires_grad=True, dtype=torch.float64)
    RT.expmap_to_quat_t(r).sum().backward()
    assert torch.isfinite(r.grad).all()


def test_quat_canonical_removes_sign_flips():
    q = np.tile(QUATS[:1], (10, 1))
    q[3:6] *= -1
    out = R.quat_canonical(q)
    assert (np.sum(out[1:] * out[:-1], axis=-1) > 0).all()
