"""The unseen-content fade's per-frame step, compiled (numba): features, nearest covering frame,
fade target, smoothing and the blend toward the input, one pass per session row.

In numpy (`NoveltyReference.distances`, `target`, `smooth`, `blend_rotations`, which fit and
report with it and which the tests hold this to) one frame of one session is ~60 small array
operations, about 4 ms: five times an LTI step. Each row is computed alone, so a session's output
does not depend on the batch it is stepped in.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .bn_skeleton import HIPS, ROOT
from .quaternion import qexp, qinv, qlog, qmul, qneg, qrot, qunit, row3, row4


@njit(cache=True, error_model="numpy")
def _heading_free(q):
    """The hips rotation without its twist about world up (`rotation_ball.split_heading`)."""
    n = math.sqrt(q[1] * q[1] + q[3] * q[3])
    if n <= 1e-12:
        return q
    return qmul((0.0, -q[1] / n, 0.0, q[3] / n), q)


@njit(cache=True, error_model="numpy")
def fade_step(
    rot_in,
    root_in,
    rot_out,
    root_out,
    w1,
    fade,
    hint,
    prev_in,
    prev_model,
    offset,
    started,
    posed,
    ref,
    knobs,
    out_rot,
    out_root,
):
    """One frame for B sessions. In: the input frames rot_in (B, J, 4), root_in (B, 3); the
    method's output rot_out, root_out; the fade state w1, fade (B, P), hint (B, P) int (the
    nearest covering frame last time, where the search starts), the previous input and method
    roots prev_in, prev_model (B, 3), the output root's horizontal offset from the method's
    offset (B, 3), started (B,) bool (prev_* hold a frame); posed (B,) bool (False: a
    controller tick, nothing to keep). `ref` = (parents, bones,
    part, anchor, centres, starts, threshold, leg) of the reference, `knobs` = (fps,
    HEIGHT_WEIGHT, SPEED_WEIGHT, START, FULL_FADE, ATTACK_FRAMES, RELEASE_FRAMES). Writes
    out_rot, out_root, and w1, fade, hint, offset in place.

    The root: its height moves toward the input's by the lower body's weight; across the ground
    it moves by the method's step and the input's mixed by that weight, so a fade never glides
    the character from the method's path to the input's (a planted foot would slide by the
    distance between them): the path it leaves behind stays as the steps made it."""
    parents, bones, part, anchor, centres, starts, threshold, leg = ref
    fps, height_w, speed_w, start, full, attack, release = knobs
    B, J = rot_in.shape[0], rot_in.shape[1]
    P = threshold.shape[0]
    grot, gpos = np.empty((J, 4)), np.empty((J, 3))
    feat = np.empty(centres.shape[1])
    for b in range(B):
        for j in range(J):
            if j == ROOT:
                grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = 0.0, 0.0, 0.0, 1.0
                gpos[j, 0], gpos[j, 1], gpos[j, 2] = 0.0, 0.0, 0.0
                continue
            q = qunit(row4(rot_in[b], j))
            if j == HIPS:
                q = _heading_free(q)
            p = parents[j]
            gp = row4(grot, p)
            d = (0.0, 0.0, 0.0) if j == HIPS else qrot(gp, row3(bones, j))
            gpos[j, 0], gpos[j, 1], gpos[j, 2] = gpos[p, 0] + d[0], gpos[p, 1] + d[1], gpos[p, 2] + d[2]
            grot[j, 0], grot[j, 1], grot[j, 2], grot[j, 3] = qmul(gp, q)
        speed = (root_in[b, 1] - prev_in[b, 1]) * fps / leg if started[b] else 0.0
        for p in range(P):
            a, n = anchor[p], 0
            for j in range(J):
                if part[j] == p and j != a:
                    for c in range(3):
                        feat[n] = gpos[j, c] / leg - gpos[a, c] / leg
                        n += 1
            if p == 0:
                feat[n] = height_w * (root_in[b, 1] / leg)
                feat[n + 1] = speed_w * speed
                n += 2
            # nearest covering frame, from last frame's: once one lies inside the radius where the
            # fade starts the target is 0 whichever it is, so a seen pose costs a few centres
            inside, best, count, first = (start * threshold[p]) ** 2, np.inf, starts[p + 1] - starts[p], hint[b, p]
            for m in range(count):
                k = starts[p] + (first + m) % count
                s = 0.0
                for i in range(n):
                    e = feat[i] - centres[k, i]
                    s += e * e
                    if s >= best:
                        break
                if s < best:
                    best, hint[b, p] = s, (k - starts[p])
                    if best <= inside:
                        break
            x = min(max((math.sqrt(best) / threshold[p] - start) / (full - start), 0.0), 1.0)
            target = x * x * (3.0 - 2.0 * x) if posed[b] else 0.0
            r1 = 1.0 / attack if target > w1[b, p] else 1.0 / release
            w1[b, p] = w1[b, p] + r1 * (target - w1[b, p])
            r2 = 1.0 / attack if w1[b, p] > fade[b, p] else 1.0 / release
            fade[b, p] = fade[b, p] + r2 * (w1[b, p] - fade[b, p])
        for j in range(J):
            w = fade[b, part[j]] if part[j] >= 0 else 0.0
            o = row4(rot_out[b], j)
            if w > 0.0:
                rel = qmul(qinv(o), row4(rot_in[b], j))
                if rel[3] < 0.0:
                    rel = qneg(rel)
                v = qlog(rel)
                o = qmul(o, qexp((w * v[0], w * v[1], w * v[2])))
            out_rot[b, j, 0], out_rot[b, j, 1], out_rot[b, j, 2], out_rot[b, j, 3] = o
        w = fade[b, part[HIPS]]
        for c in (0, 2):
            if started[b] and w > 0.0:
                offset[b, c] += w * ((root_in[b, c] - prev_in[b, c]) - (root_out[b, c] - prev_model[b, c]))
            out_root[b, c] = root_out[b, c] + offset[b, c]
        out_root[b, 1] = root_out[b, 1] + w * (root_in[b, 1] - root_out[b, 1])
