"""The unseen-content fade's per-frame step, compiled (numba): features, nearest covering frame,
fade target, smoothing and the blend toward the input, one pass per session row.

In numpy (`NoveltyReference`, which the tests hold this to) one frame of one session is ~60
small array operations, five times an LTI step. Rows are computed alone, so a session's output
does not depend on its batch; one call with few, packed arguments, since at batch 1 the call's
overhead is most of the stage's cost.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .bn_skeleton import HIPS, ROOT
from .quaternion import qexp, qinv, qlog, qmul, qneg, qrot, qunit, row3, row4

# layout of one session's fade state row (`state_width`): per part w1, fade, hint, then the
# previous input root, the previous method root, the output root's ground offset, started
W1, FADE, HINT = 0, 1, 2  # times the part count
PREV_IN, PREV_MODEL, OFFSET, STARTED = 0, 3, 6, 9  # after the 3 * parts entries
# layout of the packed float knobs (`NoveltyReference.arrays`), after the parts' thresholds
LEG, FPS, HEIGHT_W, SPEED_W, START_K, FULL_K, ATTACK_K, RELEASE_K, LIFT_K = range(9)
# rows of the packed int table (J columns): parent, part, feature kind, chain root
PARENT, PART, KIND, CHAIN_ROOT = range(4)
KIND_POSITION, KIND_LEG_END = 1, 2  # a joint's features: its position from the anchor; a leg end's reach and height


def state_width(parts: int) -> int:
    return 3 * parts + 10


@njit(cache=True, error_model="numpy")
def _heading_free(q):
    """The hips rotation without its twist about world up (`rotation_ball.split_heading`)."""
    n = math.sqrt(q[1] * q[1] + q[3] * q[3])
    if n <= 1e-12:
        return q
    return qmul((0.0, -q[1] / n, 0.0, q[3] / n), q)


@njit(cache=True, error_model="numpy")
def _lowest_foot(rot, table, bones, grot, gpos):
    """The lowest height from the hips of each leg's toes and ankle; grot, gpos: scratch."""
    low = np.inf
    for j in range(rot.shape[0]):
        if j == ROOT:
            grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = 0.0, 0.0, 0.0, 1.0
            gpos[j, 0], gpos[j, 1], gpos[j, 2] = 0.0, 0.0, 0.0
            continue
        p = table[PARENT, j]
        gp = row4(grot, p)
        d = (0.0, 0.0, 0.0) if j == HIPS else qrot(gp, row3(bones, j))
        gpos[j, 0], gpos[j, 1], gpos[j, 2] = gpos[p, 0] + d[0], gpos[p, 1] + d[1], gpos[p, 2] + d[2]
        grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = qmul(gp, qunit(row4(rot, j)))
    for j in range(rot.shape[0]):
        if table[KIND, j] == KIND_LEG_END:
            low = min(low, gpos[j, 1], gpos[table[PARENT, j], 1])
    return low


@njit(cache=True, error_model="numpy")
def fade_step(rot_in, root_in, rot_out, root_out, control, state, reference, out_rot, out_root, new, faded):
    """One frame for B sessions: the input (rot_in, root_in) and the method's output (rot_out, root_out),
    control (a controller tick has no pose to keep), state and the packed `reference`
    (`NoveltyReference.arrays`); writes out_rot, out_root, the new state `new` and fades `faded`
    into arrays the caller allocates. The root mixes the method's step and the input's by the
    lower body's weight (a fade never glides between paths), raised where the lowest foot would
    sink below the input's."""
    table, anchors_starts, floats, bones, centres = reference
    B, J = rot_in.shape[0], rot_in.shape[1]
    P = anchors_starts.shape[0] // 2
    thr = floats[:P]
    leg, fps, height_w, speed_w = floats[P + LEG], floats[P + FPS], floats[P + HEIGHT_W], floats[P + SPEED_W]
    start, full, attack, release = floats[P + START_K], floats[P + FULL_K], floats[P + ATTACK_K], floats[P + RELEASE_K]
    lift = floats[P + LIFT_K]
    new[:] = state
    faded[:] = 0.0
    grot, gpos = np.empty((J, 4)), np.empty((J, 3))
    feat = np.empty(centres.shape[1])
    for b in range(B):
        s, r = new[b], 3 * P
        started = s[r + STARTED] > 0.5
        posed = control.shape[0] == 0 or control[b, 4] <= 0.5
        for j in range(J):
            if j == ROOT:
                grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = 0.0, 0.0, 0.0, 1.0
                gpos[j, 0], gpos[j, 1], gpos[j, 2] = 0.0, 0.0, 0.0
                continue
            q = qunit(row4(rot_in[b], j))
            if j == HIPS:
                q = _heading_free(q)
            p = table[PARENT, j]
            gp = row4(grot, p)
            d = (0.0, 0.0, 0.0) if j == HIPS else qrot(gp, row3(bones, j))
            gpos[j, 0], gpos[j, 1], gpos[j, 2] = gpos[p, 0] + d[0], gpos[p, 1] + d[1], gpos[p, 2] + d[2]
            grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = qmul(gp, q)
        height = root_in[b, 1] / leg
        speed = (root_in[b, 1] - s[r + PREV_IN + 1]) * fps / leg if started else 0.0
        for p in range(P):
            a, n = anchors_starts[p], 0
            if table[PART, HIPS] == p:
                feat[0], feat[1] = height_w * height, speed_w * speed
                n = 2
            for j in range(J):
                if table[PART, j] != p:
                    continue
                if table[KIND, j] == KIND_POSITION:
                    for c in range(3):
                        feat[n + c] = (gpos[j, c] - gpos[a, c]) / leg
                    n += 3
                elif table[KIND, j] == KIND_LEG_END:
                    k = table[CHAIN_ROOT, j]
                    dx, dy, dz = gpos[j, 0] - gpos[k, 0], gpos[j, 1] - gpos[k, 1], gpos[j, 2] - gpos[k, 2]
                    feat[n] = math.sqrt(dx * dx + dy * dy + dz * dz) / leg
                    feat[n + 1] = height + (gpos[j, 1] - gpos[HIPS, 1]) / leg
                    n += 2
            # nearest covering frame, from last frame's: any inside the start radius will do
            lo, count = anchors_starts[P + p], anchors_starts[P + p + 1] - anchors_starts[P + p]
            inside, best, first = (start * thr[p]) ** 2, np.inf, int(s[HINT * P + p])
            for m in range(count):
                k = lo + (first + m) % count
                e2 = 0.0
                for i in range(n):
                    e = feat[i] - centres[k, i]
                    e2 += e * e
                    if e2 >= best:
                        break
                if e2 < best:
                    best, s[HINT * P + p] = e2, float(k - lo)
                    if best <= inside:
                        break
            x = min(max((math.sqrt(best) / thr[p] - start) / (full - start), 0.0), 1.0)
            target = x * x * (3.0 - 2.0 * x) if posed else 0.0
            w1, w = s[W1 * P + p], s[FADE * P + p]
            w1 += (1.0 / attack if target > w1 else 1.0 / release) * (target - w1)
            w += (1.0 / attack if w1 > w else 1.0 / release) * (w1 - w)
            s[W1 * P + p], s[FADE * P + p] = w1, w
            faded[b] = max(faded[b], w)
        for j in range(J):
            w = s[FADE * P + table[PART, j]] if table[PART, j] >= 0 else 0.0
            o = row4(rot_out[b], j)
            if w > 0.0:
                rel = qmul(qinv(o), row4(rot_in[b], j))
                if rel[3] < 0.0:
                    rel = qneg(rel)
                v = qlog(rel)
                o = qmul(o, qexp((w * v[0], w * v[1], w * v[2])))
            out_rot[b, j, 0], out_rot[b, j, 1], out_rot[b, j, 2], out_rot[b, j, 3] = o
        w = s[FADE * P + table[PART, HIPS]]
        for c in (0, 2):
            if started and w > 0.0:
                step_in = root_in[b, c] - s[r + PREV_IN + c]
                s[r + OFFSET + c] += w * (step_in - (root_out[b, c] - s[r + PREV_MODEL + c]))
            out_root[b, c] = root_out[b, c] + s[r + OFFSET + c]
        out_root[b, 1] = root_out[b, 1] + w * (root_in[b, 1] - root_out[b, 1])
        # a bent leg under a lowered root sinks: the root rises toward the input's floor
        lw = max(w, s[W1 * P + table[PART, HIPS]])
        if lw > 0.0:
            x = min(lw / lift, 1.0)
            sink = (root_in[b, 1] + _lowest_foot(rot_in[b], table, bones, grot, gpos)) - (
                out_root[b, 1] + _lowest_foot(out_rot[b], table, bones, grot, gpos)
            )
            out_root[b, 1] += x * x * (3.0 - 2.0 * x) * max(sink, 0.0)
        for c in range(3):
            s[r + PREV_IN + c], s[r + PREV_MODEL + c] = root_in[b, c], root_out[b, c]
        s[r + STARTED] = 1.0 if posed else 0.0
