"""BN's clavicles from its upper arms (`retarget_clavicle`): the committed relation is the one BN's
neutral data give, and it reproduces their clavicles."""

from __future__ import annotations

import numpy as np

from models.motion.retarget_clavicle import CLAVICLE_FROM_ARM, arm_and_clavicle, fit, training_motions


def predict(ac: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(F, 3) unit clavicle directions from (F, 3) upper-arm directions (chest frame), in numpy
    (the retargeting kernels apply the relation inside the chest's frame)."""
    d = u @ np.asarray(ac)[:, :3].T + np.asarray(ac)[:, 3]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_committed_relation_is_the_fit_on_bn_neutral_data():
    motions = training_motions()
    fitted = fit(motions)
    for name, ac in CLAVICLE_FROM_ARM.items():
        np.testing.assert_allclose(np.asarray(ac), fitted[name], atol=1e-3)


def test_relation_reproduces_bn_clavicles_better_than_their_mean(bn_walk):
    """On a neutral walk, the predicted clavicle lies nearer BN's own than BN's mean clavicle does."""
    for name, ac in CLAVICLE_FROM_ARM.items():
        u, d = arm_and_clavicle(bn_walk, name)
        err = np.degrees(np.arccos(np.clip(np.sum(predict(ac, u) * d, -1), -1, 1)))
        mean = d.mean(0) / np.linalg.norm(d.mean(0))
        spread = np.degrees(np.arccos(np.clip(d @ mean, -1, 1)))
        assert np.median(err) < 3.0
        assert np.mean(err) < np.mean(spread)
