"""Style-ERD training's jitter terms: the rotation acceleration the smoothness loss penalises is
the evaluation's, the loss spares the input's and the style's own motion, and the input
augmentation keeps the features one body on the rig."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.erd.features import FEATURE_DIM, NB, POS, ROOTVEL, ROT, VEL  # noqa: E402 (after the torch check)
from models.erd.model import fk_local  # noqa: E402
from models.erd.train import (  # noqa: E402
    TrainConfig,
    augment_input,
    real_rot,
    rotation_accel_t,
    smooth_loss,
)
from models.motion.assets import bandai_namco_skeleton  # noqa: E402
from models.motion.rate_metrics import rotation_acceleration  # noqa: E402
from models.motion.rotations import quat_angle, quat_exp  # noqa: E402
from models.motion.rotations_torch import quat_mul_t  # noqa: E402


def smooth_rotations(frames: int, joints: int, seed: int = 0) -> np.ndarray:
    """(frames, joints, 4) unit quaternions turning smoothly (a few degrees a frame)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None]
    axes = rng.normal(size=(joints, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angle = 0.6 * np.sin(0.15 * t + rng.uniform(0, 6, joints)) + rng.uniform(-1, 1, joints)
    return quat_exp(axes[None] * angle[..., None])


def test_acceleration_is_the_evaluations():
    q = smooth_rotations(40, 5)
    got = rotation_accel_t(torch.as_tensor(q)[None])[0].numpy()
    want = rotation_acceleration(q, fps=1.0)
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert want.max() > 1e-3  # the clip does turn


def test_smoothness_spares_the_inputs_and_the_styles_motion_and_penalises_a_pop():
    q = torch.as_tensor(smooth_rotations(24, NB, seed=1))[None]
    target = torch.zeros(1, dtype=torch.long)
    p99 = torch.full((7, NB), math.radians(2.0))
    assert smooth_loss(q, q, target, p99).item() == 0.0
    popped = q.clone()
    turn = torch.as_tensor(quat_exp(np.array([math.radians(20.0), 0.0, 0.0])), dtype=q.dtype)
    popped[0, 12, 3] = quat_mul_t(q[0, 12, 3], turn)  # a 20 degree pop on one frame
    popped = popped.requires_grad_(True)
    loss = smooth_loss(popped, q, target, p99)
    assert loss.item() > 1.0  # degrees squared, averaged over every frame and joint
    loss.backward()
    assert popped.grad is not None and torch.isfinite(popped.grad).all() and popped.grad.abs().sum() > 0
    # the same pop within the style's own acceleration is not penalised
    assert smooth_loss(popped.detach(), q, target, torch.full((7, NB), math.radians(45.0))).item() == 0.0


@pytest.fixture(scope="module")
def window():
    """Two 24-frame feature windows of one smooth body motion (rotations, positions by FK)."""
    sk = bandai_namco_skeleton()
    offsets = torch.as_tensor(sk.offsets, dtype=torch.float32)
    q = torch.as_tensor(np.stack([smooth_rotations(24, NB, seed=s) for s in (2, 3)]), dtype=torch.float32)
    height = torch.full((2, 24), 90.0)
    pos = fk_local(q, height, offsets, sk.parents)
    x = torch.zeros(2, 24, FEATURE_DIM)
    x[..., ROT] = q.flatten(2)
    x[..., POS] = pos.flatten(2)
    x[:, 1:, VEL] = (pos[:, 1:] - pos[:, :-1]).flatten(2) * 30.0
    x[..., ROOTVEL] = torch.tensor([0.0, 0.0, 120.0])
    return sk, offsets, x


def test_augmentation_off_leaves_the_window(window):
    sk, offsets, x = window
    cfg = TrainConfig(p_aug=1.0, aug_deg=0.0, aug_deg_arms=0.0, aug_scale=0.0, aug_noise_deg=0.0, aug_feat_noise=0.0)
    inp, tgt = augment_input(x, cfg, offsets, sk.parents, sk.names, torch.ones(FEATURE_DIM))
    torch.testing.assert_close(inp, x, atol=1e-3, rtol=0)
    torch.testing.assert_close(tgt, x, atol=1e-3, rtol=0)
    untouched, _ = augment_input(x, TrainConfig(p_aug=0.0), offsets, sk.parents, sk.names, torch.ones(FEATURE_DIM))
    assert untouched is x


def test_augmented_window_is_one_body_turned_by_constant_offsets(window):
    sk, offsets, x = window
    torch.manual_seed(0)
    cfg = TrainConfig(p_aug=1.0, aug_deg=10.0, aug_deg_arms=40.0, aug_scale=0.2, aug_noise_deg=0.0)
    inp, tgt = augment_input(x, cfg, offsets, sk.parents, sk.names, torch.ones(FEATURE_DIM))
    q, q2 = real_rot(x), real_rot(tgt)
    # each joint turned by one rotation over the whole window, at most its bound
    angle = torch.as_tensor(np.degrees(quat_angle(q.double().numpy(), q2.double().numpy())))
    assert (angle.amax(1) - angle.amin(1)).max() < 0.1
    arms = torch.tensor([("Shoulder" in n or "UpperArm" in n) for n in sk.names[1:]])
    assert angle[..., ~arms].max() <= 10.01 and angle[..., arms].max() <= 40.01
    assert angle.max() > 2.0
    # the target's positions are the turned rotations' by FK; its velocities their differences
    pos = fk_local(q2, tgt[..., POS][..., 1], offsets, sk.parents)
    torch.testing.assert_close(tgt[..., POS], pos.flatten(2), atol=1e-3, rtol=0)
    speed = tgt[..., ROOTVEL] / x[..., ROOTVEL].clamp_min(1e-6)
    vel = (pos[:, 1:] - pos[:, :-1]).flatten(2) * 30.0 + (tgt[:, 1:, ROOTVEL] - x[:, 1:, ROOTVEL]).repeat(1, 1, NB)
    torch.testing.assert_close(tgt[:, 1:, VEL], vel, atol=1e-2, rtol=0)
    assert ((speed[..., 2] - 1).abs() <= 0.2 + 1e-5).all()
    # the network's input: the target's rotations, its positions and velocities with noise
    torch.testing.assert_close(inp[..., ROT], tgt[..., ROT])
    assert 0 < (inp[..., POS] - tgt[..., POS]).abs().mean() < 0.2
