"""The compiled quaternion helpers agree with scipy's rotations on random unit quaternions."""

import numpy as np
from scipy.spatial.transform import Rotation

from models.motion import quaternion as Q

RNG = np.random.default_rng(7)


def _random_quats(n: int) -> np.ndarray:
    return Rotation.random(n, random_state=RNG).as_quat()  # scalar-last, like the project


def test_product_inverse_and_rotation_match_scipy():
    a, b = _random_quats(50), _random_quats(50)
    v = RNG.normal(size=(50, 3))
    for i in range(50):
        expect = (Rotation.from_quat(a[i]) * Rotation.from_quat(b[i])).as_quat()
        got = np.array(Q.qmul(tuple(a[i]), tuple(b[i])))
        assert min(np.abs(got - expect).max(), np.abs(got + expect).max()) < 1e-12
        assert np.allclose(Q.qrot(tuple(a[i]), tuple(v[i])), Rotation.from_quat(a[i]).apply(v[i]))
        ident = Q.qmul(Q.qinv(tuple(a[i])), tuple(a[i]))
        assert np.allclose(ident, (0.0, 0.0, 0.0, 1.0))


def test_log_and_exp_invert_each_other_on_the_shortest_arc():
    for q in _random_quats(50):
        v = np.array(Q.qlog(tuple(q)))
        assert np.linalg.norm(v) <= np.pi + 1e-12
        assert np.allclose(v, Rotation.from_quat(q).as_rotvec())
        back = np.array(Q.qexp(tuple(v)))
        assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-12
    assert Q.qexp((0.0, 0.0, 0.0)) == (0.0, 0.0, 0.0, 1.0)


def test_between_carries_u_onto_v_including_opposite_directions():
    u = RNG.normal(size=(20, 3))
    v = RNG.normal(size=(20, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for a, b in zip(u, v):
        q = Q.between(tuple(a), tuple(b))
        assert np.allclose(Q.qrot(q, tuple(a)), b)
        opposite = Q.between(tuple(a), tuple(-a))
        assert np.allclose(Q.qrot(opposite, tuple(a)), -a)


def test_yaw_turns_about_up_and_nlerp_takes_the_shorter_arc():
    for yaw in RNG.uniform(-np.pi, np.pi, 20):
        expect = Rotation.from_rotvec([0.0, yaw, 0.0]).as_quat()
        assert np.allclose(Q.qyaw(yaw), expect)
    a, b = _random_quats(20), _random_quats(20)
    for p, q in zip(a, b):
        # t and -t are one rotation: nlerp blends toward whichever lies on a's hemisphere
        for t in (q, -q):
            mid = np.array(Q.nlerp(tuple(p), tuple(t), 0.5))
            near = q if np.dot(p, q) >= 0.0 else -q
            assert np.allclose(mid, (p + near) / np.linalg.norm(p + near))
        assert np.allclose(Q.nlerp(tuple(p), tuple(q), 0.0), p)
