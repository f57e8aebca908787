"""The shared foot planter (`models.motion.feet`): planted toes and ankles stay put, the path stays
the model's, sessions are independent, and the leg IK it uses reaches its target."""

from __future__ import annotations

import numpy as np
import pytest

from models.motion import feet_kernels
from models.motion.bn_skeleton import HIPS
from models.motion.feet import STATE_SHAPES, model_rig_planter
from models.motion.rotations import quat_apply, quat_mul
from models.motion.skeleton import fk

from .reference.foot_pitch import ankle_heights, followed_pitch, sole_heading, sole_pitch
from .reference.foot_slide import planted_slide


def _plant(
    planter, roots: np.ndarray, rotations: np.ndarray, hints: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step a batch of clips (B, F, 3), (B, F, J, 4) through `planter` frame by frame, with the
    model's contact `hints` (B, 2) on every frame if given."""
    state = planter.init_state(len(roots))
    out_root, out_rot, contacts = np.empty_like(roots), np.empty_like(rotations), np.empty(roots.shape[:2] + (2,), bool)
    for t in range(roots.shape[1]):
        out_root[:, t], out_rot[:, t], contacts[:, t], state = planter(state, roots[:, t], rotations[:, t], hints=hints)
    return out_root, out_rot, contacts


def _skating(walk, speedup: float):
    """The walk with its root travelling `speedup` times as far as its legs carry it: feet skate."""
    root = walk.translations[:, HIPS].copy()
    root[:, [0, 2]] = root[0, [0, 2]] + speedup * (root[:, [0, 2]] - root[0, [0, 2]])
    return root


def _with(walk, root, rotations):
    translations = walk.translations.copy()
    translations[:, HIPS] = root
    return type(walk)(walk.skeleton, rotations, translations, walk.fps, walk.euler_orders)


def test_planted_toes_stay_put_when_the_root_outruns_the_strides(bn_walk):
    skating_root = _skating(bn_walk, 1.3)
    before = np.median(planted_slide(_with(bn_walk, skating_root, bn_walk.rotations))["toe"])
    root, rot, contacts = _plant(model_rig_planter(bn_walk.fps), skating_root[None], bn_walk.rotations[None])
    after = planted_slide(_with(bn_walk, root[0], rot[0]))
    real = np.median(planted_slide(bn_walk)["toe"])
    assert before > 10.0  # cm/s: the skating input
    assert np.median(after["toe"]) <= max(2 * real, 0.5)
    # the legs lengthen the strides (follow=0) until a held foot is stretched too far; then the root
    # gives way: the path lies between the legs' own and the model's
    path = lambda r: np.linalg.norm(np.diff(r[:, [0, 2]], axis=0), axis=-1).sum()  # noqa: E731
    assert path(bn_walk.translations[:, HIPS]) < path(root[0]) < path(skating_root)
    assert 0.3 < contacts.mean() < 0.9  # a walk: each foot down about 60 % of the time


def _knee_bend_acceleration(motion_rotations: np.ndarray, skeleton) -> np.ndarray:
    """|second difference| of each knee's bend angle, degrees per frame squared: a pop is a spike."""
    bends = [
        np.degrees(2 * np.arccos(np.abs(motion_rotations[:, skeleton.index(k), 3]).clip(0, 1)))
        for k in ("LowerLeg_L", "LowerLeg_R")
    ]
    return np.concatenate([np.abs(np.diff(b, 2)) for b in bends])


def test_a_hold_that_stretches_the_leg_does_not_pop_the_knee(bn_walk):
    """Held feet on a skating root pull the legs toward full reach; with exact IK the knee snaps
    straight and pops bent again on release (42 degrees/frame^2 here, the real walk at most 18)."""
    _, rot, _ = _plant(model_rig_planter(bn_walk.fps), _skating(bn_walk, 1.3)[None], bn_walk.rotations[None])
    real = _knee_bend_acceleration(bn_walk.rotations, bn_walk.skeleton)
    assert _knee_bend_acceleration(rot[0], bn_walk.skeleton).max() <= real.max()


def test_following_the_feet_moves_the_root_by_the_strides_instead(bn_walk):
    skating_root = _skating(bn_walk, 1.3)
    root, rot, _ = _plant(model_rig_planter(bn_walk.fps, follow=1.0), skating_root[None], bn_walk.rotations[None])
    path = lambda r: np.linalg.norm(np.diff(r[:, [0, 2]], axis=0), axis=-1).sum()  # noqa: E731
    assert path(root[0]) < 0.9 * path(skating_root)
    assert abs(path(root[0]) - path(bn_walk.translations[:, HIPS])) < 0.15 * path(bn_walk.translations[:, HIPS])
    assert np.median(planted_slide(_with(bn_walk, root[0], rot[0]))["toe"]) < 1.0


def test_a_real_walk_is_left_almost_as_it_is(bn_walk):
    real_root = bn_walk.translations[:, HIPS]
    root, rot, _ = _plant(model_rig_planter(bn_walk.fps), real_root[None], bn_walk.rotations[None])
    _, moved = fk(rot[0], _with(bn_walk, real_root, rot[0]).translations, bn_walk.skeleton.parents)
    _, real = fk(bn_walk.rotations, bn_walk.translations, bn_walk.skeleton.parents)
    assert np.median(np.linalg.norm(moved - real, axis=-1)) < 0.2  # cm: the pose
    assert np.percentile(np.linalg.norm(moved - real, axis=-1), 99) < 5.0
    assert np.linalg.norm(root[0] - real_root, axis=-1).max() < 3.0  # cm over ~10 s: the path


def test_feet_in_the_air_are_left_alone(bn_walk):
    high = bn_walk.translations[:, HIPS] + [0.0, 60.0, 0.0]  # a jump's flight, held
    root, rot, contacts = _plant(model_rig_planter(bn_walk.fps), high[None], bn_walk.rotations[None])
    assert not contacts.any()
    np.testing.assert_array_equal(rot[0], bn_walk.rotations)
    np.testing.assert_allclose(root[0], high)


def test_a_foot_on_the_floor_at_the_first_frame_stays_there_when_the_next_pops(bn_walk):
    """A session starts standing: a model whose second frame jumps the body 4 cm (120 cm/s, too
    fast to count as a touch-down) keeps the feet that stood on the floor in the first frame."""
    planter = model_rig_planter(bn_walk.fps)
    root = np.repeat(bn_walk.translations[:1, HIPS], 2, axis=0)
    root[1, 0] += 4.0
    rot = np.repeat(bn_walk.rotations[:1], 2, axis=0)
    out_root, out_rot, contacts = _plant(planter, root[None], rot[None])
    assert contacts[0, 0].any() and (contacts[0, 0] == contacts[0, 1]).all()
    toes = [bn_walk.skeleton.index(n) for n in ("Toes_L", "Toes_R")]
    pos = _with(bn_walk.slice(0, 2), out_root[0], out_rot[0]).global_positions()[:, toes]
    moved = np.linalg.norm((pos[1] - pos[0])[:, [0, 2]], axis=-1)
    assert (moved[contacts[0, 0]] < 0.5).all() and (moved[~contacts[0, 0]] > 3.5).all()


def test_sessions_are_planted_independently(bn_walk):
    planter = model_rig_planter(bn_walk.fps)
    roots = np.stack([_skating(bn_walk, 1.3), bn_walk.translations[:, HIPS], _skating(bn_walk, 0.7)])
    rots = np.repeat(bn_walk.rotations[None], 3, axis=0)
    together = _plant(planter, roots, rots)
    for b in range(3):
        alone = _plant(planter, roots[b : b + 1], rots[b : b + 1])
        for a, t in zip(alone, together):
            np.testing.assert_array_equal(a[0], t[b])


def test_a_state_from_before_the_planter_is_brought_up_to_date(bn_walk):
    planter = model_rig_planter(bn_walk.fps)
    old = {"started": np.ones(2, bool), "lock_anchor": np.zeros((2, 2, 3))}
    new = planter.upgrade_state(old, 2)
    assert set(STATE_SHAPES) <= set(new) and new["started"] is old["started"]
    with pytest.raises(ValueError, match="feet_rel"):
        planter({**planter.init_state(1), "feet_rel": np.zeros((1, 2, 3))}, np.zeros((1, 3)), bn_walk.rotations[:1])


def test_two_bone_ik_reaches_its_target_and_keeps_the_foot_turned_as_it_was(bn_walk):
    sk, m = bn_walk.skeleton, bn_walk
    up, low, foot, toe = (sk.index(n) for n in ("UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L"))
    rng = np.random.default_rng(4)
    for t in (10, 50, 90):
        rots = m.rotations[t : t + 1]
        g_old, p_old = fk(rots, m.translations[t : t + 1], sk.parents)
        target = p_old[:, foot] + rng.uniform(-4, 4, 3)
        hip = m.translations[t : t + 1, HIPS] + quat_apply(rots[:, HIPS], sk.offsets[up][None])
        new = rots.copy()
        row = lambda a: tuple(np.asarray(a, np.float64)[0])  # noqa: E731
        leg = (row(rots[:, up]), row(rots[:, low]), row(rots[:, foot]))
        bones = (tuple(sk.offsets[low]), tuple(sk.offsets[foot]), tuple(sk.offsets[toe]))
        new[0, up], new[0, low], new[0, foot] = feet_kernels.two_bone_ik(
            row(rots[:, HIPS]), leg, row(hip), bones, row(target), 0.0
        )
        g_new, p_new = fk(new, m.translations[t : t + 1], sk.parents)
        np.testing.assert_allclose(p_new[:, foot], target, atol=1e-3)  # cm
        assert abs(abs(np.sum(g_old[0, foot] * g_new[0, foot])) - 1) < 1e-9


@pytest.mark.parametrize("side", ["L", "R"])
def test_two_bone_ik_bends_a_straight_knee_about_its_hinge(bn_walk, side):
    """A straight leg (the hinge floor holds knees at BN's least real bend, straight) has no bend
    plane of its own: the IK bends it toward the toes, near BN's knee hinge (the knee's local y,
    real bends positive, `weights/lti/hinges.npz`; off it by the foot's turn out, here < 9 deg),
    not about a bone offset's stray millimetre (0.24 rad off the hinge) or backwards."""
    sk, m, t = bn_walk.skeleton, bn_walk, 40
    up, low, foot, toe = (sk.index(f"{n}_{side}") for n in ("UpperLeg", "LowerLeg", "Foot", "Toes"))
    rots = m.rotations[t : t + 1].copy()
    rots[:, low] = (0.0, 0.0, 0.0, 1.0)  # straight
    _, p = fk(rots, m.translations[t : t + 1], sk.parents)
    hip = p[0, up]
    target = p[0, foot] + 2.0 * (hip - p[0, foot]) / np.linalg.norm(hip - p[0, foot])  # 2 cm nearer the hip
    row = lambda a: tuple(np.asarray(a, np.float64)[0])  # noqa: E731
    leg = (row(rots[:, up]), row(rots[:, low]), row(rots[:, foot]))
    bones = (tuple(sk.offsets[low]), tuple(sk.offsets[foot]), tuple(sk.offsets[toe]))
    new = rots.copy()
    new[0, up], new[0, low], new[0, foot] = feet_kernels.two_bone_ik(
        row(rots[:, HIPS]), leg, tuple(hip), bones, tuple(target), 0.0
    )
    np.testing.assert_allclose(fk(new, m.translations[t : t + 1], sk.parents)[1][0, foot], target, atol=1e-3)
    x, y, z, w = new[0, low]
    bend = 2.0 * np.arctan2(y, w)  # about the hinge: a 2 cm shorter leg needs ~0.45 rad
    assert bend > 0.3 and np.hypot(x, z) < 0.15 * abs(np.sin(bend / 2))


def test_an_inactive_session_gets_its_frame_back_as_it_is(bn_walk):
    """A style at intensity 0 returns the input: nothing is planted for it."""
    planter = model_rig_planter(bn_walk.fps)
    state = planter.init_state(1)
    skating_root = _skating(bn_walk, 1.3)
    for t in range(bn_walk.num_frames):
        root, rot, contacts, state = planter(
            state, skating_root[t : t + 1], bn_walk.rotations[t : t + 1], np.zeros(1, bool)
        )
        np.testing.assert_array_equal(root[0], skating_root[t])
        np.testing.assert_array_equal(rot[0], bn_walk.rotations[t])
        assert not contacts.any()


@pytest.mark.parametrize("hint_speed, plants", [(np.inf, True), (150.0, True), (100.0, False)])
def test_a_hinted_foot_plants_only_below_the_hint_speed(bn_walk, hint_speed, plants):
    """A foot touching down while it travels 4 cm in a frame (120 cm/s, with the root: no push
    back, too fast for an unhinted touch-down) plants on the model's hint only below `hint_speed`."""
    planter = model_rig_planter(bn_walk.fps, hint_speed=hint_speed)
    root = np.repeat(bn_walk.translations[:1, HIPS], 2, axis=0)
    root[0, 1] += 60.0  # in the air, then down 4 cm further on
    root[1, 0] += 4.0
    rot = np.repeat(bn_walk.rotations[:1], 2, axis=0)
    contacts = _plant(planter, root[None], rot[None], hints=np.ones((1, 2), bool))[2][0]
    assert not contacts[0].any() and contacts[1].any() == plants


@pytest.mark.parametrize("hinted", [True, False])
def test_a_hinted_foot_pulls_a_floor_left_low_up(bn_walk, hinted):
    """A frame sunk 20 cm leaves the floors low (they creep back up by `floor_rise`). Standing
    back up with the model's hint pulls them to `HINT_FLOOR_RISE` below the feet at once, so the
    feet, 8 cm lower the next frame, plant (the root drifts 1 cm a frame); unhinted, they are
    still far above the old floor and do not."""
    planter = model_rig_planter(bn_walk.fps)
    root = np.repeat(bn_walk.translations[:1, HIPS], 4, axis=0)
    root[1, 1] -= 20.0
    root[3, 1] -= 8.0
    root[:, 0] += np.arange(4.0)
    rot = np.repeat(bn_walk.rotations[:1], 4, axis=0)
    contacts = _plant(planter, root[None], rot[None], hints=np.full((1, 2), hinted))[2][0]
    assert not contacts[2].any() and contacts[3].all() == hinted


def _held_offsets(
    planter, roots: np.ndarray, rotations: np.ndarray, hints: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One clip through `planter` (with the model's contact `hints` (F, 2) if given): (planted
    roots (F, 3), planted legs (F, 2), each leg's horizontal IK offset (F, 2))."""
    state = planter.init_state(1)
    out_root, contacts, offsets = np.empty_like(roots), np.empty((len(roots), 2), bool), np.empty((len(roots), 2))
    for t in range(len(roots)):
        h = None if hints is None else hints[t : t + 1]
        r, _, c, state = planter(state, roots[t : t + 1], rotations[t : t + 1], hints=h)
        out_root[t], contacts[t] = r[0], c[0]
        offsets[t] = np.linalg.norm(state["feet_offset"][0][:, [0, 2]], axis=-1)
    return out_root, contacts, offsets


def test_a_root_that_stands_still_under_striding_legs_gives_way_instead_of_the_holds(bn_walk):
    """The walk's legs over a root that does not travel: every planted foot slides back at walking
    speed. Without `give` holds let go at `max_offset` and snap (the feet plant a fifth of the
    time, sliding); with it the root takes what a hold would need past `give`, so the feet plant
    as in the walk, no hold grows past `give`, and the root travels by the strides."""
    still = _skating(bn_walk, 0.0)  # bobs as walked, travels nowhere
    path = lambda r: np.linalg.norm(np.diff(r[:, [0, 2]], axis=0), axis=-1).sum()  # noqa: E731
    _, c0, _ = _held_offsets(model_rig_planter(bn_walk.fps, max_offset=8.0), still, bn_walk.rotations)
    root, contacts, offsets = _held_offsets(
        model_rig_planter(bn_walk.fps, max_offset=8.0, give=7.0), still, bn_walk.rotations
    )
    _, real, _ = _held_offsets(
        model_rig_planter(bn_walk.fps, max_offset=8.0), bn_walk.translations[:, HIPS], bn_walk.rotations
    )
    assert c0.mean() < 0.4 < contacts.mean()
    assert abs(contacts.mean() - real.mean()) < 0.05
    assert offsets[contacts].max() <= 7.0 + 1e-6
    assert 0.7 * path(bn_walk.translations[:, HIPS]) < path(root) < 1.1 * path(bn_walk.translations[:, HIPS])


def test_give_off_leaves_the_planter_as_it_was(bn_walk):
    """`give` 0 (the networks' planters) changes nothing: the same frames bit for bit as a planter
    without the setting."""
    skating = _skating(bn_walk, 1.3)[None]
    a = _plant(model_rig_planter(bn_walk.fps), skating, bn_walk.rotations[None])
    b = _plant(model_rig_planter(bn_walk.fps, give=0.0), skating, bn_walk.rotations[None])
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def test_the_root_move_for_two_held_feet_is_the_shortest_into_both_discs():
    """`feet_kernels._least_in_discs`: in both discs, the same with the feet swapped (no side is
    preferred), and no longer than any point of a fine grid over both discs."""
    rng = np.random.default_rng(5)
    r = 7.0
    for _ in range(200):
        a = rng.uniform(-12, 12, 2)
        b = a + rng.uniform(-1, 1, 2) * rng.uniform(0.0, 2 * r / np.sqrt(2))
        if np.linalg.norm(a - b) > 2 * r:
            continue
        g = np.array(feet_kernels._least_in_discs(a[0], a[1], b[0], b[1], r))
        h = np.array(feet_kernels._least_in_discs(b[0], b[1], a[0], a[1], r))
        np.testing.assert_allclose(g, h, atol=1e-9)
        assert np.linalg.norm(g - a) <= r + 1e-6 and np.linalg.norm(g - b) <= r + 1e-6
        xs = np.stack(np.meshgrid(np.linspace(-20, 20, 161), np.linspace(-20, 20, 161)), -1).reshape(-1, 2)
        inside = (np.linalg.norm(xs - a, axis=1) <= r) & (np.linalg.norm(xs - b, axis=1) <= r)
        if inside.any():
            assert np.linalg.norm(g) <= np.linalg.norm(xs[inside], axis=1).min() + 1e-6


def test_a_foot_the_model_calls_down_is_held_to_hint_offset(bn_walk):
    """The walk's legs over a still root, the model's hints calling each foot down whenever the
    real walk plants it: without `hint_offset` a hold lets go past `max_offset`; with it the
    hinted holds are kept (two feet pulled apart grow up to it), so the feet stay held longer.
    Without hints `hint_offset` changes nothing."""
    still = _skating(bn_walk, 0.0)
    _, real, _ = _held_offsets(model_rig_planter(bn_walk.fps), bn_walk.translations[:, HIPS], bn_walk.rotations)
    plain = model_rig_planter(bn_walk.fps, max_offset=8.0)
    longer = model_rig_planter(bn_walk.fps, max_offset=8.0, hint_offset=16.0)
    _, c8, o8 = _held_offsets(plain, still, bn_walk.rotations, hints=real)
    _, c16, o16 = _held_offsets(longer, still, bn_walk.rotations, hints=real)
    assert o8[c8].max() <= 8.0 + 1e-6 < o16[c16].max() <= 16.0 + 1e-6
    assert c16.mean() > c8.mean()
    for x, y in zip(_held_offsets(plain, still, bn_walk.rotations), _held_offsets(longer, still, bn_walk.rotations)):
        np.testing.assert_array_equal(x, y)


def test_the_root_move_for_two_held_feet_does_not_jump_as_their_discs_part():
    """`feet_kernels.into_both_discs` either side of the discs touching (centres 2r apart) gives
    nearly the same move, at any share; parted further, at share 0 foot a keeps its hold within r,
    and the move changes little with the share."""
    rng = np.random.default_rng(7)
    r = 5.0
    for _ in range(200):
        a = rng.uniform(-12, 12, 2)
        u = rng.normal(size=2)
        u /= np.linalg.norm(u)
        share = rng.uniform()
        inside, outside = (
            np.array(feet_kernels.into_both_discs(a[0], a[1], *(a + d * u), r, share))
            for d in (2 * r - 1e-7, 2 * r + 1e-7)
        )
        np.testing.assert_allclose(inside, outside, atol=1e-3)
        b = a + 3 * r * u
        assert np.linalg.norm(np.array(feet_kernels.into_both_discs(a[0], a[1], b[0], b[1], r, 0.0)) - a) <= r + 1e-9
        near = (np.array(feet_kernels.into_both_discs(a[0], a[1], b[0], b[1], r, s)) for s in (share, share + 1e-7))
        np.testing.assert_allclose(*near, atol=1e-5)


def test_of_two_held_feet_the_one_the_animation_moved_less_is_served():
    """`feet_kernels.served_share`: the slower foot gets the root's move (its hold stays within
    r), both share while they move alike, and the width is a speed (the same at any rate)."""
    r, a, b = 5.0, np.array([-6.0, 0.0]), np.array([6.0, 0.0])
    for fps in (30.0, 120.0):
        fast = 2.0 * feet_kernels.SERVE_SPEED / fps  # cm this frame: twice the width
        for a_moved, b_moved, served in ((0.0, fast, a), (fast, 0.0, b)):
            move = np.array(feet_kernels.into_both_discs(*a, *b, r, feet_kernels.served_share(a_moved, b_moved, fps)))
            assert np.linalg.norm(move - served) <= r + 1e-9
        assert feet_kernels.served_share(fast, fast, fps) == 0.5


def test_the_root_gives_way_no_faster_than_give_speed(bn_walk):
    """`give_speed` bounds the root's move off its path: at 0 the planter is the one without
    `give`, frame for frame; at 30 cm/s the still root travels part of the strides' way (the
    holds take the rest, up to `max_offset`, and let go past it)."""
    still = _skating(bn_walk, 0.0)[None]
    path = lambda r: np.linalg.norm(np.diff(r[:, [0, 2]], axis=0), axis=-1).sum()  # noqa: E731
    none = _plant(model_rig_planter(bn_walk.fps, max_offset=8.0), still, bn_walk.rotations[None])
    stopped = _plant(
        model_rig_planter(bn_walk.fps, max_offset=8.0, give=5.0, give_speed=0.0), still, bn_walk.rotations[None]
    )
    for x, y in zip(none, stopped, strict=True):
        np.testing.assert_array_equal(x, y)
    slow = _plant(
        model_rig_planter(bn_walk.fps, max_offset=8.0, give=5.0, give_speed=30.0), still, bn_walk.rotations[None]
    )
    free = _plant(model_rig_planter(bn_walk.fps, max_offset=8.0, give=5.0), still, bn_walk.rotations[None])
    assert path(none[0][0]) < path(slow[0][0]) < path(free[0][0])


# --------------------------------------------------------------------------- the feet's pitch


def _turned_feet(walk, chains: np.ndarray) -> np.ndarray:
    """The walk's rotations with each foot turned 25° toe-down about its own x and 15° about its
    own y: a foot landing flat, and toed out."""
    from scipy.spatial.transform import Rotation

    rot = walk.rotations.copy()
    turn = (Rotation.from_euler("x", 25, degrees=True) * Rotation.from_euler("y", 15, degrees=True)).as_quat()
    for chain in chains:
        rot[:, chain[2]] = quat_mul(rot[:, chain[2]], turn)
    return rot


def _pitched(walk, rotations: np.ndarray, share: float, above: float = 0.0) -> np.ndarray:
    """`rotations` (F, J, 4) through `follow_pitch` toward the walk's, every frame a session whose
    ankles are `above` their floors."""
    planter = model_rig_planter(walk.fps)
    F, root = len(rotations), walk.translations[:, HIPS]
    ankles = np.stack([ankle_heights(rotations, root, planter.hips, c, planter.offsets) for c in planter.chains], -1)
    floor = np.repeat((ankles - above)[..., None], 2, axis=-1)  # (F, 2 legs, ankle and toe)
    before = feet_kernels.Feet(
        np.ones(F), root.copy(), root.copy(), np.zeros((F, 2, 2, 3)), np.zeros((F, 2)), np.zeros((F, 2)),
        np.zeros((F, 2, 3)), floor,
    )  # fmt: skip
    out = rotations.copy()
    feet_kernels.follow_pitch(walk.rotations, out, root, before, planter._params, share)
    want = followed_pitch(
        walk.rotations, rotations, root, floor[..., 0], planter.hips, planter.chains, planter.offsets, share
    )
    np.testing.assert_allclose(out, want, atol=1e-9)  # the numpy reference
    return out


def _input_lifts(walk, planter) -> np.ndarray:
    """(F, 2) how far each of the walk's ankles is above its lower one: where the input's foot is."""
    at_root = np.zeros((walk.num_frames, 3))
    ankles = np.stack(
        [ankle_heights(walk.rotations, at_root, planter.hips, c, planter.offsets) for c in planter.chains], -1
    )
    return ankles - ankles.min(-1, keepdims=True)


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_a_toe_rises_its_share_of_the_way_to_the_inputs_pitch_and_nothing_else_moves(bn_walk, share):
    """While the input's foot is down (within PITCH_LOW of its other ankle); while it is up (from
    PITCH_HIGH) the foot keeps its own pitch: an input on another phase of its step lends none."""
    planter = model_rig_planter(bn_walk.fps)
    hips, chains, offsets = planter.hips, planter.chains, planter.offsets
    turned = _turned_feet(bn_walk, chains)
    out = _pitched(bn_walk, turned, share)
    lifts = _input_lifts(bn_walk, planter)
    for leg, chain in enumerate(chains):
        down, up = lifts[:, leg] <= feet_kernels.PITCH_LOW, lifts[:, leg] >= feet_kernels.PITCH_HIGH
        assert down.mean() > 0.3 and up.mean() > 0.1  # a walk: each foot down, then swinging
        before, want = (sole_pitch(r, hips, chain, offsets) for r in (turned, bn_walk.rotations))
        rise = np.maximum(want - before, 0.0)  # a toe only rises toward the input's
        got = sole_pitch(out, hips, chain, offsets)
        np.testing.assert_allclose(got[down], (before + share * rise)[down], atol=1e-6)
        np.testing.assert_array_equal(out[up, chain[2]], turned[up, chain[2]])
        assert share == 0.0 or (rise[down] > np.radians(5)).mean() > 0.5  # the toe-down turn is there to undo
        heading = [sole_heading(r, hips, chain, offsets) for r in (turned, out)]  # a toed-out foot stays so
        assert np.abs(np.angle(np.exp(1j * (heading[1] - heading[0])))).max() < 1e-5
    feet = chains[:, 2]
    np.testing.assert_array_equal(np.delete(out, feet, axis=1), np.delete(turned, feet, axis=1))  # only the feet


@pytest.mark.parametrize("above,moved", [(2.0, 1.0), (6.5, 0.5), (12.0, 0.0)])
def test_a_foot_in_the_air_keeps_its_pitch(bn_walk, above, moved):
    """The pitch follows the input's fully up to PITCH_LOW over the floor, not at all from PITCH_HIGH."""
    assert feet_kernels.PITCH_LOW < 6.5 < feet_kernels.PITCH_HIGH < 12.0
    planter = model_rig_planter(bn_walk.fps)
    hips, chains, offsets = planter.hips, planter.chains, planter.offsets
    turned = _turned_feet(bn_walk, chains)
    out = _pitched(bn_walk, turned, 1.0, above)
    share = np.clip((feet_kernels.PITCH_HIGH - above) / (feet_kernels.PITCH_HIGH - feet_kernels.PITCH_LOW), 0, 1)
    assert share == pytest.approx(moved, abs=0.01)
    lifts = _input_lifts(bn_walk, planter)
    for leg, chain in enumerate(chains):
        down = lifts[:, leg] <= feet_kernels.PITCH_LOW
        before, want = (sole_pitch(r, hips, chain, offsets) for r in (turned, bn_walk.rotations))
        rise = np.maximum(want - before, 0.0)
        np.testing.assert_allclose(
            sole_pitch(out, hips, chain, offsets)[down], (before + share * rise)[down], atol=1e-6
        )
