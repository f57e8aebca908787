import numpy as np
import torch

from models.motion import bvh
from models.motion.skeleton import fk, fk_torch, from_bvh, to_bvh


def test_rest_pose_fk_matches_offsets(bn_walk, cmu_walk):
    for motion in (bn_walk, cmu_walk):
        sk = motion.skeleton
        J = sk.num_joints
        ident = np.tile([0.0, 0.0, 0.0, 1.0], (J, 1))
        _, pos = fk(ident, sk.offsets, sk.parents)
        for j, p in enumerate(sk.parents):
            if p >= 0:
                np.testing.assert_allclose(pos[j] - pos[p], sk.offsets[j], atol=1e-9)
        np.testing.assert_allclose(pos, sk.rest_positions(), atol=1e-9)


def test_torch_fk_matches_numpy_and_is_differentiable(bn_walk):
    m = bn_walk.slice(0, 40)
    g_rot, g_pos = m.global_transforms()
    rot_t = torch.tensor(m.rotations, requires_grad=True)
    t_rot, t_pos = fk_torch(rot_t, torch.tensor(m.translations), m.skeleton.parents)
    np.testing.assert_allclose(t_pos.detach().numpy(), g_pos, atol=1e-8)
    np.testing.assert_allclose(np.abs((t_rot.detach().numpy() * g_rot).sum(-1)), 1.0, atol=1e-10)
    t_pos.sum().backward()
    assert torch.isfinite(rot_t.grad).all() and rot_t.grad.abs().sum() > 0
    # batched: (B, F, J, ...) gives the same as one clip at a time
    b_rot = torch.stack([torch.tensor(m.rotations)] * 3)
    _, b_pos = fk_torch(b_rot, torch.tensor(m.translations).expand(3, -1, -1, -1), m.skeleton.parents)
    np.testing.assert_allclose(b_pos[2].numpy(), g_pos, atol=1e-8)


def test_motion_to_bvh_and_back_preserves_pose(index):
    for clip in (next(c for c in index if c.dataset == "bandai-namco-1"), next(c for c in index if c.dataset == "cmu")):
        original = bvh.read(clip.path)
        motion = from_bvh(original)
        rebuilt = from_bvh(bvh.parse(bvh.dumps(to_bvh(motion, template=original))))
        np.testing.assert_allclose(rebuilt.global_positions(), motion.global_positions(), atol=1e-3)
        default_layout = from_bvh(bvh.parse(bvh.dumps(to_bvh(motion))))
        np.testing.assert_allclose(default_layout.global_positions(), motion.global_positions(), atol=1e-3)


def test_bandai_namco_stands_up_and_walks_forward(bn_walk):
    pos = bn_walk.global_positions()
    sk = bn_walk.skeleton
    head, toe = pos[:, sk.index("Head"), 1], pos[:, sk.index("Toes_L"), 1]
    assert 130 < head.mean() < 190 and toe.min() > -2 and toe.min() < 10  # cm, Y up, feet on the floor
