from dataclasses import replace

import numpy as np

from models.motion.features import WORLD_MIRROR, compute_features, foot_contacts, mirror
from models.motion.rotations import quat_exp, quat_mul


def _perturb_from(motion, t):
    """Same motion up to frame t, different from t+1 on."""
    rng = np.random.default_rng(0)
    rot = motion.rotations.copy()
    noise = quat_exp(rng.normal(scale=0.3, size=rot[t + 1 :].shape[:-1] + (3,)))
    rot[t + 1 :] = quat_mul(rot[t + 1 :], noise)
    tr = motion.translations.copy()
    tr[t + 1 :, 1] += rng.normal(scale=10.0, size=tr[t + 1 :, 1].shape)
    return replace(motion, rotations=rot, translations=tr)


def test_features_are_causal(bn_walk):
    motion, t = bn_walk.slice(0, 90), 50
    a, b = compute_features(motion), compute_features(_perturb_from(motion, t))
    for name in a.__dataclass_fields__:
        fa, fb = getattr(a, name), getattr(b, name)
        np.testing.assert_array_equal(fa[: t + 1], fb[: t + 1], err_msg=name)
        assert not np.array_equal(fa[t + 1 :], fb[t + 1 :]) or name == "contacts"


def test_walk_features_make_sense(bn_walk):
    f = compute_features(bn_walk)
    speed = f.root_velocity[:, 2].mean()
    assert 60 < speed < 200  # cm/s forward in the facing frame
    assert abs(f.root_velocity[:, 0].mean()) < 0.2 * speed  # little sideways drift
    assert 0.3 < f.contacts.mean() < 0.8  # each foot planted part of the time
    # the left and right foot alternate: not planted-together all the time
    assert (f.contacts[:, 0] != f.contacts[:, 1]).mean() > 0.2
    hips = bn_walk.skeleton.index("Hips")
    np.testing.assert_allclose(f.local_positions[:, hips, [0, 2]], 0.0, atol=1e-9)


def test_contacts_scale_with_the_skeleton(cmu_walk):
    f = compute_features(cmu_walk)
    assert 0.2 < f.contacts.mean() < 0.9


def test_mirror_is_exact_on_the_bandai_namco_skeleton(bn_walk):
    m = mirror(bn_walk)
    pos, mpos = bn_walk.global_positions(), m.global_positions()
    np.testing.assert_allclose(
        mpos, WORLD_MIRROR * pos[:, bn_walk.skeleton.mirror_map()], atol=1e-4
    )  # cm; float32 cache
    twice = mirror(m)
    np.testing.assert_allclose(np.abs((twice.rotations * bn_walk.rotations).sum(-1)), 1.0, atol=1e-6)
    # mirrored contacts swap feet
    c = foot_contacts(pos, bn_walk.skeleton, bn_walk.fps)
    mc = foot_contacts(mpos, bn_walk.skeleton, bn_walk.fps)
    np.testing.assert_array_equal(mc, c[:, ::-1])
