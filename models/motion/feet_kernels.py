"""Compiled kernels (numba) for `feet.FootPlanter` and the two-bone leg IK it uses.

Quaternions are 4-tuples (x, y, z, w), the project's scalar-last order; everything is float64.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from .quaternion import add3, axis_angle, between, cross, dot3, qinv, qmul, qrot, qunit, row3, row4, sub3


class Feet(NamedTuple):
    """The foot planter's state (`feet.STATE_SHAPES`, in its order), B sessions."""

    started: np.ndarray  # (B,)
    root: np.ndarray  # (B, 3) the planted root
    model_root: np.ndarray  # (B, 3) the model's
    rel: np.ndarray  # (B, 2, 2, 3) each leg's ankle and toe from the root
    contact: np.ndarray  # (B, 2) planted legs
    point: np.ndarray  # (B, 2) held point (0 ankle, 1 toe)
    offset: np.ndarray  # (B, 2, 3) the legs' IK offsets
    floor: np.ndarray  # (B, 2, 2) each leg's ankle and toe floor


@njit(cache=True, error_model="numpy")
def _nrm(v):
    n = max(math.sqrt(dot3(v, v)), 1e-9)
    return (v[0] / n, v[1] / n, v[2] / n)


@njit(cache=True, error_model="numpy")
def _cos(u, v):
    return min(max(dot3(_nrm(u), _nrm(v)), -1.0), 1.0)


# --------------------------------------------------------------------------- two-bone leg IK


@njit(cache=True, error_model="numpy")
def soft_reach(d, d0, reach, soft):
    """The hip-ankle distance for a target `d` away: `d` up to `reach - soft`, then eased toward `reach`
    (near full extension exact IK snaps the knee straight). soft = 0: exact."""
    start = max(reach - soft, d0)
    if soft <= 0.0 or d <= start:
        return min(d, reach)
    room = reach - start
    if room <= 1e-9:
        return start
    return start + room * (1.0 - math.exp(-(d - start) / room))


# The bend plane of a near-straight leg: hip-knee x hip-ankle plus this much of the plane through
# the hip-ankle line and the toes: a straight knee has no plane of its own, and a knee bends toward
# the toes. Squared weight, as `retarget.HINGE_FALLBACK`.
POLE_WEIGHT = 0.07**2


@njit(cache=True, error_model="numpy")
def two_bone_ik(gh, leg, a, bones, target, soft):
    """Analytic two-bone IK: the leg's local rotations putting the ankle at `target`, foot unturned."""
    r_up, r_low, r_foot = leg
    off_low, off_foot, off_toe = bones
    ga = qmul(gh, r_up)
    gb = qmul(ga, r_low)
    gf = qmul(gb, r_foot)
    lab, lcb = math.sqrt(dot3(off_low, off_low)), math.sqrt(dot3(off_foot, off_foot))
    at = sub3(target, a)
    ac = sub3(add3(add3(a, qrot(ga, off_low)), qrot(gb, off_foot)), a)
    lat = max(soft_reach(math.sqrt(dot3(at, at)), math.sqrt(dot3(ac, ac)), lab + lcb - 1e-3, soft), 1e-3)
    ac_ab_1 = math.acos(min(max((lcb * lcb - lab * lab - lat * lat) / (-2.0 * lab * lat), -1.0), 1.0))
    ba_bc_1 = math.acos(min(max((lat * lat - lab * lab - lcb * lcb) / (-2.0 * lab * lcb), -1.0), 1.0))
    toe = qrot(gf, off_toe)
    # twice: a bend off the leg's plane misses the distance slightly; the second pass fixes it
    for _ in range(2):
        b = add3(a, qrot(ga, off_low))
        c = add3(b, qrot(gb, off_foot))
        ac = sub3(c, a)
        ac_ab_0 = math.acos(_cos(ac, sub3(b, a)))
        ba_bc_0 = math.acos(_cos(sub3(a, b), sub3(c, b)))
        own = cross(_nrm(ac), _nrm(sub3(b, a)))
        toes = _nrm(cross(_nrm(ac), _nrm(toe)))
        w = math.sqrt(dot3(own, own))
        axis = _nrm(
            (w * own[0] + POLE_WEIGHT * toes[0], w * own[1] + POLE_WEIGHT * toes[1], w * own[2] + POLE_WEIGHT * toes[2])
        )
        ga2 = qmul(axis_angle(axis, ac_ab_1 - ac_ab_0), ga)
        gb = qmul(axis_angle(axis, ba_bc_1 - ba_bc_0), qmul(ga2, qmul(qinv(ga), gb)))
        ga = ga2
    gb2 = gb
    b2 = add3(a, qrot(ga2, off_low))
    c2 = add3(b2, qrot(gb2, off_foot))
    w2 = between(_nrm(sub3(c2, a)), _nrm(at))
    ga3 = qmul(w2, ga2)
    gb3 = qmul(w2, gb2)
    return qmul(qinv(gh), ga3), qmul(qinv(ga3), gb3), qmul(qinv(gb3), gf)


# --------------------------------------------------------------------------- the planter


@njit(cache=True, error_model="numpy")
def leg_points(rot, hips, chain, offsets, out):
    """Ankle and toe of leg `chain` relative to the root (at the Hips) into out (2, 3)."""
    g = row4(rot, hips)
    p = qrot(g, row3(offsets, chain[0]))
    for k in range(1, 4):
        g = qmul(g, row4(rot, chain[k - 1]))
        p = add3(p, qrot(g, row3(offsets, chain[k])))
        if k >= 2:
            out[k - 2, 0], out[k - 2, 1], out[k - 2, 2] = p


# --------------------------------------------------------------------------- the feet's pitch

# Share of the way a foot's toe rises to the input's pitch against the ground, whole up to PITCH_LOW
# above the ankle's floor and none from PITCH_HIGH (rig units, cm on the models' rig), for the
# output's foot and the input's alike: in the air, or while the input's foot is, a foot is the
# method's own (`follow_pitch`; validation, docs/eval/ablation.md).
PITCH_SHARE = 0.75
PITCH_LOW, PITCH_HIGH = 3.0, 10.0


@njit(cache=True, error_model="numpy")
def _low(height):
    """1 up to PITCH_LOW above the floor, 0 from PITCH_HIGH, linear between."""
    return min(max((PITCH_HIGH - height) / (PITCH_HIGH - PITCH_LOW), 0.0), 1.0)


@njit(cache=True, error_model="numpy")
def _elevation(g, sole):
    """The elevation (radians) of the direction `sole` turned by `g`, and that direction."""
    v = _nrm(qrot(g, sole))
    return math.asin(min(max(v[1], -1.0), 1.0)), v


@njit(cache=True, error_model="numpy")
def follow_pitch(rot_in, out_rot, root, before, planter, share):
    """Each foot of `out_rot` (B, J, 4) near the floor whose toe points lower than the input's
    (`rot_in`) raised in place about the level axis across it, `share` of the way: a heel strikes
    at least as the input's does (a method predicting each joint alone lands a foot flat while the
    leg swings, and it skids); only while the input's foot is down too (an input on another
    phase of its step lends no pitch). The sole is the toe bone laid level in the rest pose (the
    toe bone points straight down at a push-off); its heading, a style's toe-out, stays. `root`
    (B, 3), the planter's state `before` and parameters (`FootPlanter`) place the ankles over
    their floors; the input's ankle counts as down near its lower ankle."""
    hips, chains, offsets, floors = planter[0], planter[1], planter[2], planter[3]
    points, ankles_in, unit_in = np.empty((2, 3)), np.empty(2), np.empty((rot_in.shape[1], 4))
    for b in range(out_rot.shape[0]):
        # the rows read below (the hips, each leg's hip joint, knee and ankle) made unit: a client's need not be
        for j in (hips, chains[0, 0], chains[0, 1], chains[0, 2], chains[1, 0], chains[1, 1], chains[1, 2]):
            unit_in[j, 0], unit_in[j, 1], unit_in[j, 2], unit_in[j, 3] = qunit(row4(rot_in[b], j))
        for leg in range(2):
            leg_points(unit_in, hips, chains[leg], offsets, points)
            ankles_in[leg] = points[0, 1]
        for leg in range(2):
            up, low, ft, toe = chains[leg, 0], chains[leg, 1], chains[leg, 2], chains[leg, 3]
            n = math.sqrt(offsets[toe, 0] ** 2 + offsets[toe, 2] ** 2)
            if n < 1e-9:  # a toe straight below the ankle: no sole to pitch
                continue
            leg_points(out_rot[b], hips, chains[leg], offsets, points)
            floor = before.floor[b, leg, 0] if before.started[b] else floors[0]
            # both feet near the ground: the output's over its floor, the input's over its lower ankle
            lift_in = ankles_in[leg] - min(ankles_in[0], ankles_in[1])
            near = share * _low(root[b, 1] + points[0, 1] - floor) * _low(lift_in)
            if near <= 0.0:
                continue
            sole = (offsets[toe, 0] / n, 0.0, offsets[toe, 2] / n)
            shin_in = qmul(qmul(row4(unit_in, hips), row4(unit_in, up)), row4(unit_in, low))
            shin = qmul(qmul(row4(out_rot[b], hips), row4(out_rot[b], up)), row4(out_rot[b], low))
            foot = qmul(shin, row4(out_rot[b], ft))
            want, _ = _elevation(qmul(shin_in, row4(unit_in, ft)), sole)
            have, v = _elevation(foot, sole)
            level = math.sqrt(v[0] * v[0] + v[2] * v[2])
            if want <= have or level < 1e-6:  # the toe as high as the input's, or the sole upright
                continue
            pitch = axis_angle((-v[2] / level, 0.0, v[0] / level), near * (want - have))  # about v x up
            q = qmul(qinv(shin), qmul(pitch, foot))
            out_rot[b, ft, 0], out_rot[b, ft, 1], out_rot[b, ft, 2], out_rot[b, ft, 3] = q


# cm: a hinted foot lifts its floor at once to at most this far below it; a floor left low would
# otherwise creep up for seconds, holding no foot meanwhile.
HINT_FLOOR_RISE = 10.0


@njit(cache=True, error_model="numpy")
def _into_disc(x, z, cx, cz, r):
    """The point of the disc of radius r about (cx, cz) nearest (x, z)."""
    ex, ez = x - cx, z - cz
    d = math.sqrt(ex * ex + ez * ez)
    if d <= r:
        return x, z
    return cx + ex * r / d, cz + ez * r / d


@njit(cache=True, error_model="numpy")
def _in_disc(x, z, cx, cz, r):
    return (x - cx) ** 2 + (z - cz) ** 2 <= r * r * (1.0 + 1e-9) + 1e-12


@njit(cache=True, error_model="numpy")
def _least_in_discs(ax, az, bx, bz, r):
    """The shortest (x, z) in both discs of radius r about a and b, which meet."""
    best, best_x, best_z = math.inf, 0.0, 0.0
    for cx, cz in ((0.0, 0.0), _into_disc(0.0, 0.0, ax, az, r), _into_disc(0.0, 0.0, bx, bz, r)):
        if _in_disc(cx, cz, ax, az, r) and _in_disc(cx, cz, bx, bz, r) and cx * cx + cz * cz < best:
            best, best_x, best_z = cx * cx + cz * cz, cx, cz
    if best < math.inf:
        return best_x, best_z
    dx, dz = bx - ax, bz - az
    d = max(math.sqrt(dx * dx + dz * dz), 1e-12)
    h = math.sqrt(max(r * r - 0.25 * d * d, 0.0))
    mx, mz = 0.5 * (ax + bx), 0.5 * (az + bz)
    for sign in (-1.0, 1.0):
        cx, cz = mx - sign * h * dz / d, mz + sign * h * dx / d
        if cx * cx + cz * cz < best:
            best, best_x, best_z = cx * cx + cz * cz, cx, cz
    return best_x, best_z


# cm/s: two held feet spread apart, one this much faster: the root serves the slower alone
# (`served_share`); moving alike, both share, so the move does not jump as they swap. Not tuned.
SERVE_SPEED = 30.0


@njit(cache=True, error_model="numpy")
def served_share(a_moved, b_moved, fps):
    """`into_both_discs`' share for two held feet moved a_moved and b_moved: 0 serves a, 1 b."""
    return min(max(0.5 + (a_moved - b_moved) * fps / (2.0 * SERVE_SPEED), 0.0), 1.0)


@njit(cache=True, error_model="numpy")
def root_gives(b, ox, oz, height, rel, floor, margin, before, give, fps):
    """Session b's root move so no held leg needs more than `give` (Kovar et al. 2002)."""
    _, prev_root, _, prev_rel, prev_contact, prev_point, prev_offset, _ = before
    n, ax, az, a_moved, bx, bz, b_moved = 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for leg in range(2):
        if not prev_contact[b, leg]:
            continue
        k = prev_point[b, leg]
        if height + rel[b, leg, k, 1] >= floor[b, leg, k] + margin:
            continue  # lifting: the hold ends this frame anyway
        mx = ox + rel[b, leg, k, 0] - prev_root[b, 0] - prev_rel[b, leg, k, 0]
        mz = oz + rel[b, leg, k, 2] - prev_root[b, 2] - prev_rel[b, leg, k, 2]
        px, pz = prev_offset[b, leg, 0] - mx, prev_offset[b, leg, 2] - mz
        if n == 0:
            ax, az, a_moved = px, pz, mx * mx + mz * mz
        else:
            bx, bz, b_moved = px, pz, mx * mx + mz * mz
        n += 1
    if n == 0:
        return 0.0, 0.0
    if n == 1:
        return _into_disc(0.0, 0.0, ax, az, give)
    return into_both_discs(ax, az, bx, bz, give, served_share(math.sqrt(a_moved), math.sqrt(b_moved), fps))


@njit(cache=True, error_model="numpy")
def into_both_discs(ax, az, bx, bz, r, share):
    """The root's move for two held feet: the shortest in both discs, else `share` of the way between
    their nearest points; continuous, so the root does not shake."""
    dx, dz = bx - ax, bz - az
    d2 = dx * dx + dz * dz
    if d2 <= 4.0 * r * r:
        return _least_in_discs(ax, az, bx, bz, r)
    d = math.sqrt(d2)
    ux, uz = dx / d, dz / d
    return ax + r * ux + share * (d - 2.0 * r) * ux, az + r * uz + share * (d - 2.0 * r) * uz


@njit(cache=True, error_model="numpy")
def plant_feet(root, rot, active, hints, before, after, out_rot, planter):
    """One frame of `feet.FootPlanter` for B sessions; inactive sessions pass, their state keeping up."""
    started, prev_root, prev_model_root, prev_rel, prev_contact, prev_point, prev_offset, prev_floor = before
    _, out_root, _, rel, contacts, point, offset, floor = after
    (
        hips, chains, offsets, floors, margin, floor_rise, onset_speed, max_offset, decay, follow, soft, fps, hint_speed,
        give, give_speed, hint_offset,
    ) = planter  # fmt: skip
    for b in range(root.shape[0]):
        for leg in range(2):
            leg_points(rot[b], hips, chains[leg], offsets, rel[b, leg])
        for leg in range(2):
            for k in range(2):  # ankle, toe: its floor follows it down at once and up slowly, or
                # (`HINT_FLOOR_RISE`) at once toward it where the model calls the foot down
                height = root[b, 1] + rel[b, leg, k, 1]
                rise = prev_floor[b, leg, k] + floor_rise / fps if started[b] else floors[k]
                if hints[b, leg] and started[b]:
                    rise = max(rise, height - HINT_FLOOR_RISE)
                floor[b, leg, k] = min(height, rise)
        # the root: the model's motion, or (by `follow`, or the leash) the held points' of planted legs
        ox, oz = root[b, 0], root[b, 2]
        if started[b]:
            dx, dz = root[b, 0] - prev_model_root[b, 0], root[b, 2] - prev_model_root[b, 2]
            fx, fz, n, held = 0.0, 0.0, 0, 0.0
            for leg in range(2):
                if prev_contact[b, leg]:
                    k = prev_point[b, leg]
                    fx -= rel[b, leg, k, 0] - prev_rel[b, leg, k, 0]
                    fz -= rel[b, leg, k, 2] - prev_rel[b, leg, k, 2]
                    n += 1
                    held = max(held, math.sqrt(prev_offset[b, leg, 0] ** 2 + prev_offset[b, leg, 2] ** 2))
            if n > 0:
                # the leash: past a quarter of max_offset the root gives way, all of it at max_offset
                f = max(follow, min(max((held / max_offset - 0.25) / 0.75, 0.0), 1.0))
                dx = f * fx / n + (1.0 - f) * dx
                dz = f * fz / n + (1.0 - f) * dz
            ox, oz = prev_root[b, 0] + dx, prev_root[b, 2] + dz
            if give > 0.0:
                # the root takes what held feet would need past `give`, at most `give_speed`
                gx, gz = root_gives(b, ox, oz, root[b, 1], rel, floor, margin, before, give, fps)
                gn = math.sqrt(gx * gx + gz * gz)
                if gn > give_speed / fps:
                    gx, gz = gx * give_speed / fps / gn, gz * give_speed / fps / gn
                ox, oz = ox + gx, oz + gz
        if not active[b]:
            ox, oz = root[b, 0], root[b, 2]
        out_root[b, 0], out_root[b, 1], out_root[b, 2] = ox, root[b, 1], oz
        # per leg: which point is on the ground, and how far the leg must move to keep it there
        for leg in range(2):
            low_ankle = root[b, 1] + rel[b, leg, 0, 1] < floor[b, leg, 0] + margin
            low_toe = root[b, 1] + rel[b, leg, 1, 1] < floor[b, leg, 1] + margin
            k = 1 if low_toe else 0
            point[b, leg] = k
            # horizontal motion of that point since the last frame, this frame's root against the last
            mx = ox + rel[b, leg, k, 0] - (prev_root[b, 0] + prev_rel[b, leg, k, 0])
            mz = oz + rel[b, leg, k, 2] - (prev_root[b, 2] + prev_rel[b, leg, k, 2])
            ex, ez = prev_offset[b, leg, 0], prev_offset[b, leg, 2]
            planted = False
            if not started[b]:
                planted = low_toe or low_ankle  # a session starts standing: a foot on the floor stays there
            elif low_toe or low_ankle:
                if prev_contact[b, leg]:
                    planted = True
                    ex, ez = ex - mx, ez - mz  # hold: undo the point's motion
                elif (
                    math.sqrt(mx * mx + mz * mz) * fps < (hint_speed if hints[b, leg] else onset_speed)
                    or mx * (ox - prev_root[b, 0]) + mz * (oz - prev_root[b, 2])
                    < (ox - prev_root[b, 0]) ** 2 + (oz - prev_root[b, 2]) ** 2
                ):
                    # touch-down (slow, or pushing back against the root's path): hold from here on
                    planted = True
            if planted and math.sqrt(ex * ex + ez * ez) > (hint_offset if hints[b, leg] else max_offset):
                planted = False  # the animation has walked away from the hold: let the foot go
            if not active[b]:
                planted, ex, ez = False, 0.0, 0.0
            if not planted:
                ex, ez = ex * decay, ez * decay
            contacts[b, leg] = planted
            offset[b, leg, 0], offset[b, leg, 1], offset[b, leg, 2] = ex, 0.0, ez
            if ex * ex + ez * ez < 1e-12:
                continue
            chain = chains[leg]
            up, low, ft = chain[0], chain[1], chain[2]
            gh = row4(out_rot[b], hips)
            hip = add3((ox, root[b, 1], oz), qrot(gh, row3(offsets, up)))
            ankle = (ox + rel[b, leg, 0, 0] + ex, root[b, 1] + rel[b, leg, 0, 1], oz + rel[b, leg, 0, 2] + ez)
            leg_rot = (row4(out_rot[b], up), row4(out_rot[b], low), row4(out_rot[b], ft))
            bones = (row3(offsets, low), row3(offsets, ft), row3(offsets, chain[3]))
            r_up, r_low, r_foot = two_bone_ik(gh, leg_rot, hip, bones, ankle, soft)
            for i in range(4):
                out_rot[b, up, i], out_rot[b, low, i], out_rot[b, ft, i] = r_up[i], r_low[i], r_foot[i]
