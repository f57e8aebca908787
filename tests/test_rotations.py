import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from models.motion import rotations as R
from models.motion import rotations_torch as RT

rng = np.random.default_rng(0)
QUATS = Rotation.random(500, random_state=1).as_quat()


@pytest.mark.parametrize("order", ["ZXY", "ZYX", "XYZ", "YXZ"])
def test_euler_round_trip(order):
    angles = rng.uniform(-170, 170, size=(200, 3))
    angles[:, 1] = rng.uniform(-85, 85, size=200)  # away from gimbal lock for a unique inverse
    q = R.euler_to_quat(angles, order)
    np.testing.assert_allclose(R.quat_to_euler(q, order), angles, atol=1e-8)


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
    back = R.matrix_to_quat(R.quat_to_matrix(QUATS))
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


def test_log_and_exp_match_scipy_including_zero_angle():
    rotvec = Rotation.from_quat(QUATS).as_rotvec()
    rotvec[0] = 0.0
    rotvec[1] = 1e-7
    q = R.quat_exp(rotvec)
    np.testing.assert_allclose(R.quat_to_matrix(q), Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(R.quat_log(q), rotvec, atol=1e-9)
    assert np.all(np.linalg.norm(R.quat_log(QUATS), axis=-1) <= np.pi + 1e-12)


def test_quat_canonical_removes_sign_flips():
    q = np.tile(QUATS[:1], (10, 1))
    q[3:6] *= -1
    out = R.quat_canonical(q)
    assert (np.sum(out[1:] * out[:-1], axis=-1) > 0).all()
