"""Per-frame (streaming) CMU <-> BN retargeting against the clip-level `retarget`, on real walks."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motion, select
from models.motion.assets import cmu_skeleton
from models.motion.bn_skeleton import PRIMARY_CHILD
from models.motion.humanoid import CMU_TO_BN, leg_length, rig_kind
from models.motion.retarget import _CLAVICLES, contact_height, default_rig, retarget
from models.motion.retarget_stream import FrameRetargeter, trunk_bones
from models.motion.rotations import matrix_to_quat as mat_to_quat
from models.motion.rotations import quat_to_matrix as quat_to_mat
from models.motion.skeleton import Motion, fk

from .clips import angle_deg

# one walk per CMU naming (`rig_kind`): Xia (cgspeed names, 'cmu'), CMU 131 (bvh11 names, 'cmu-bvh11')
WALKS = {"cmu": ("xia", "neutral_walk_01_000"), "cmu-bvh11": ("cmu", "131_01")}
FRAMES = 150


@pytest.fixture(scope="module")
def rig():
    return default_rig()


@pytest.fixture(scope="module")
def walks(rig) -> dict[str, tuple[Motion, FrameRetargeter]]:
    index = build_index(["cmu", "xia"])
    out = {}
    for variant, (dataset, name) in WALKS.items():
        motion = load_motion(select(index, dataset=dataset, name=name)[0]).slice(0, FRAMES)
        assert rig_kind(motion.skeleton) == variant
        out[variant] = (motion, FrameRetargeter(motion.skeleton, rig))
    return out


def _bn_positions(rig, hips: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    sk = rig.skeleton
    trans = np.broadcast_to(sk.offsets, rotations.shape[:-1] + (3,)).copy()
    trans[:, sk.index("Hips")] = hips
    return fk(rotations, trans, sk.parents)[1]


def test_matrix_conversions_round_trip():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4))
    q = np.concatenate([q, np.eye(4), [[0.5**0.5, 0.5**0.5, 0, 0], [0, 0.5**0.5, 0, -(0.5**0.5)]]])
    back = mat_to_quat(quat_to_mat(q))
    assert np.all(back[:, 3] >= 0)
    assert angle_deg(back, q).max() < 1e-5


@pytest.mark.parametrize("variant", list(WALKS))
def test_per_frame_equals_clip_level(walks, rig, variant):
    motion, fr = walks[variant]
    ref = retarget(motion, rig, fps=motion.fps)
    hips, rot = fr.to_model(motion.translations[:, 0], motion.rotations)
    assert rot.shape == ref.rotations.shape and hips.shape == (motion.num_frames, 3)
    assert angle_deg(rot, ref.rotations).max() < 1e-3  # same rotations (up to quaternion sign)
    ref_hips = ref.translations[:, rig.skeleton.index("Hips")]
    np.testing.assert_allclose(hips[:, [0, 2]], ref_hips[:, [0, 2]], atol=1e-9)  # same scaled root
    dy = hips[:, 1] - ref_hips[:, 1]
    assert np.ptp(dy) < 1e-9  # differs by one constant only: fixed offset vs the clip's toe percentile
    assert abs(dy[0]) < 6.0  # cm; Xia's floor sits ~1.2 CMU units lower than CMU's (see test below)


def test_rest_offset_puts_cmu_toes_on_the_floor(walks, rig):
    """CMU files keep the toes about where the default source floor assumes them; Xia files need
    their own floor, which then lands the BN toes near the BN contact height too."""
    toes = [rig.skeleton.index("Toes_L"), rig.skeleton.index("Toes_R")]
    motion, fr = walks["cmu-bvh11"]
    pos = _bn_positions(rig, *fr.to_model(motion.translations[:, 0], motion.rotations))
    assert abs(contact_height(pos[:, toes, 1]) - rig.floor) < 2.0
    motion, fr = walks["cmu"]  # Xia
    smap = CMU_TO_BN["cmu"]
    src_toes = [motion.skeleton.index(smap["Toes_L"]), motion.skeleton.index(smap["Toes_R"])]
    xia = FrameRetargeter(motion.skeleton, rig, source_floor=contact_height(motion.global_positions()[:, src_toes, 1]))
    pos = _bn_positions(rig, *xia.to_model(motion.translations[:, 0], motion.rotations))
    # 2.0 cm: the standing offset is set in BN's natural pose, whose feet are not both flat
    assert abs(contact_height(pos[:, toes, 1]) - rig.floor) < 2.5


@pytest.mark.parametrize("variant", list(WALKS))
def test_round_trip_reproduces_the_source(walks, variant):
    motion, fr = walks[variant]
    root, rot = motion.translations[:, 0], motion.rotations
    back_root, back_rot = fr.to_source(*fr.to_model(root, rot), rot)
    np.testing.assert_allclose(back_root, root, atol=1e-9)
    trans = motion.translations.copy()
    trans[:, 0] = back_root
    pos = fk(back_rot, trans, motion.skeleton.parents)[1]
    smap = CMU_TO_BN[variant]
    mapped = [motion.skeleton.index(n) for n in smap.values()]
    err = np.linalg.norm(pos - motion.global_positions(), axis=-1)
    assert err[:, mapped].max() < 1e-6 * leg_length(motion.skeleton)  # brief asked < 2 %
    assert err.max() < 1e-6 * leg_length(motion.skeleton)  # unmapped joints too
    assert angle_deg(back_rot, rot).max() < 1e-4
    unmapped = [j for j in range(motion.skeleton.num_joints) if j not in mapped]
    np.testing.assert_array_equal(back_rot[:, unmapped], rot[:, unmapped])  # kept as the client sent them


@pytest.mark.parametrize("variant", list(WALKS))
def test_to_source_points_bones_where_bn_does(walks, rig, variant):
    """A BN pose that is not the client's (here: the walk 40 frames later) comes back with every
    matched source bone along its BN bone, the client's frame only filling in unmapped joints: the
    trunk's as its chords at BN's shares of its length (`retarget_stream.trunk_bones`), within two
    degrees: a chord crosses client joints that turn with their own BN joint's change. The
    limbs' bones come back within the tilt that lays BN's hinge child into its hinge plane
    (`retarget` module docstring): a client's limb turns as BN's does, so a round trip is exact.
    Not the clavicles: BN's follow its upper arms (`retarget_clavicle`), the client's collars
    turn with BN's clavicles' change."""
    motion, fr = walks[variant]
    root, rot = motion.translations[:, 0], motion.rotations
    hips, bn = fr.to_model(root, rot)
    n = motion.num_frames - 40
    new_root, new_rot = fr.to_source(hips[40:], bn[40:], rot[:n])
    trans = motion.translations[:n].copy()
    trans[:, 0] = new_root
    src_pos = fk(new_rot, trans, motion.skeleton.parents)[1]
    bn_pos = _bn_positions(rig, hips[40:], bn[40:])
    sk, bsk, smap = motion.skeleton, rig.skeleton, CMU_TO_BN[variant]
    trunk = trunk_bones(sk, fr.humanoid.roles, bsk)
    for a, b in PRIMARY_CHILD.items():
        if a in _CLAVICLES:
            continue
        s = src_pos[:, sk.index(smap[b])] - src_pos[:, sk.index(smap[a])]
        if a in trunk:
            s = sum(w * (src_pos[:, k] - src_pos[:, sk.parents[k]]) for k, w in trunk[a])
        t = bn_pos[:, bsk.index(b)] - bn_pos[:, bsk.index(a)]
        cos = np.sum(s * t, -1) / np.linalg.norm(s, axis=-1) / np.linalg.norm(t, axis=-1)
        limb = a.split("_")[0] in ("UpperArm", "LowerArm", "UpperLeg", "LowerLeg")
        angle = np.degrees(np.arccos(cos.clip(-1, 1)))
        if a.startswith("Foot_"):  # turned by the rigs' flat-foot pitches (`retarget_stream._sole_terms`)
            angle -= angle[0]
        assert np.abs(angle).max() < (5.0 if limb else 2.0 if a in trunk else 1e-4), (a, b)
    # and the hips: same place after scaling, but for the height the root rises by for the feet
    # (`FrameRetargeter._drop`), which the client's new pose sets on the way back
    want = motion.global_positions()[40:, 0]
    np.testing.assert_allclose(src_pos[:, 0, [0, 2]], want[:, [0, 2]], atol=1e-9)
    assert np.abs(src_pos[:, 0, 1] - want[:, 1]).max() * fr.scale < 1.0  # cm


@pytest.mark.parametrize("variant", list(WALKS))
def test_batch_equals_per_frame_and_is_causal(walks, variant):
    """A clip's frames at once equal the same frames one at a time with the stream's state
    carried (as the service calls it), both ways; several streams' frames in one call equal
    each stream's own; and no frame's output depends on a later frame."""
    motion, fr = walks[variant]
    root, rot = motion.translations[:, 0], motion.rotations
    hips, bn = fr.to_model(root, rot)
    back_root, back_rot = fr.to_source(hips, bn, rot)
    state = fr.init_state()
    for t in range(motion.num_frames):
        h1, b1 = fr.to_model(root[t], rot[t][None], state)  # a single frame, (3,) root accepted
        np.testing.assert_allclose(h1[0], hips[t], atol=1e-12)
        np.testing.assert_allclose(b1[0], bn[t], atol=1e-12)
        r1, s1 = fr.to_source(hips[t : t + 1], bn[t : t + 1], rot[t : t + 1], state)
        np.testing.assert_allclose(r1[0], back_root[t], atol=1e-12)
        np.testing.assert_allclose(s1[0], back_rot[t], atol=1e-12)
    # three streams at once (rows: streams), each at its own place in the walk
    starts, states = np.array([0, 40, 90]), fr.init_state(3)
    alone = [fr.to_model(root[s : s + 30], rot[s : s + 30]) for s in starts]
    for k in range(30):
        h3, b3 = fr.to_model(root[starts + k], rot[starts + k], states)
        for i in range(3):
            np.testing.assert_allclose(h3[i], alone[i][0][k], atol=1e-12)
            np.testing.assert_allclose(b3[i], alone[i][1][k], atol=1e-12)
    # causality: scrambling every later frame leaves frame t's output as it was
    rng = np.random.default_rng(1)
    t = 60
    rot2, root2 = rot.copy(), root.copy()
    rot2[t + 1 :] = rng.normal(size=rot2[t + 1 :].shape)
    root2[t + 1 :] += rng.normal(size=root2[t + 1 :].shape) * 10
    h2, b2 = fr.to_model(root2, rot2)
    np.testing.assert_allclose(h2[t], hips[t], atol=1e-12)
    np.testing.assert_allclose(b2[t], bn[t], atol=1e-12)
    r2, s2 = fr.to_source(h2, b2, rot2)
    np.testing.assert_allclose(r2[t], back_root[t], atol=1e-12)
    np.testing.assert_allclose(s2[t], back_rot[t], atol=1e-12)


def test_a_bad_state_is_refused(walks):
    motion, fr = walks["cmu"]
    with pytest.raises(ValueError, match="hinge state"):
        fr.to_model(motion.translations[:2, 0], motion.rotations[:2], np.zeros((2, 4, 3)))
    with pytest.raises(ValueError, match="in place"):
        fr.to_model(motion.translations[:2, 0], motion.rotations[:2], np.asfortranarray(fr.init_state(2)))


def test_cmu_skeleton():
    sk = cmu_skeleton()
    assert rig_kind(sk) == "cmu" and sk.num_joints == 31 and sk.names[0] == "Hips"
    fr = FrameRetargeter(sk)
    assert 5.0 < fr.scale < 6.2  # cm per CMU unit, by leg length
