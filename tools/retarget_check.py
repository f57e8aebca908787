"""How much jitter retargeting adds: p99 rotation acceleration of each BN joint against the same
body part of the source, clip by clip.

A flip in the retargeter (a limb root's twist turning by ~180 degrees between two frames, a
quaternion hemisphere change fed into a product) shows as a spike in the second difference of a
joint's rotation, which no mocap source has. So per BN joint the retargeted local rotation's p99
acceleration is compared with the source's rotation of the matched client joint relative to its
nearest matched ancestor (client chains may hold extra joints; the relative rotation spans the
same body segment as BN's local rotation). "back": a styled BN frame (the retargeted one with
constant local offsets, as a model's output differs from its input) mapped back onto the
client's rig, the same measure per client joint.

    python -m tools.retarget_check [--fps 30 120] [--joints]

(`python -m tools.bench retarget` times the retargeter.)
"""

from __future__ import annotations

import argparse

import numpy as np

from models.motion.humanoid import bn_joints_of, bn_segments
from models.motion.resample import resample
from models.motion.retarget_stream import FrameRetargeter, _path_terms
from models.motion.rotations import matrix_to_quat, quat_exp, quat_inv, quat_log, quat_mul, quat_to_matrix
from models.motion.skeleton import Motion

# Joint groups the acceptance compares (BN names); leaves the retargeter holds still are left out.
GROUPS = {
    "hips": ("Hips",),
    "spine": ("Spine", "Chest", "Neck"),
    "arms": ("Shoulder_L", "Shoulder_R", "UpperArm_L", "UpperArm_R", "LowerArm_L", "LowerArm_R"),
    "legs": ("UpperLeg_L", "UpperLeg_R", "LowerLeg_L", "LowerLeg_R", "Foot_L", "Foot_R"),
}
BOUND = 1.2  # retargeted p99 acceleration may be at most this times the source's (the gate)

# A style's constant change to some BN local rotations (rotation vectors, radians): arms out and
# forward, knees and spine bent, for the way back.
STYLE_OFFSETS = {
    "Chest": (0.15, 0.0, 0.1),
    "UpperArm_L": (0.0, 0.3, 0.3),
    "UpperArm_R": (0.0, -0.3, -0.3),
    "LowerArm_L": (0.0, 0.0, 0.4),
    "LowerArm_R": (0.0, 0.0, -0.4),
    "LowerLeg_L": (0.0, 0.0, 0.3),
    "LowerLeg_R": (0.0, 0.0, 0.3),
}


def rotation_acceleration(q: np.ndarray) -> np.ndarray:
    """(F - 2, K) degrees per frame squared: the change of each joint's frame-to-frame turn (the
    turn as a rotation vector in the joint's previous frame), from rotations (F, K, 4)."""
    turn = quat_log(quat_mul(quat_inv(q[:-1]), q[1:]))
    return np.degrees(np.linalg.norm(np.diff(turn, axis=0), axis=-1))


def relative_rotations(rotations: np.ndarray, parents: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """(F, K, 4) per (joint, anchor) pair the joint's world rotation relative to the anchor's
    (anchor -1: the world rotation), from local quaternions (F, J, 4)."""
    mats = quat_to_matrix(rotations)
    world = mats.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            world[:, j] = world[:, p] @ mats[:, j]
    out = [world[:, j] if a < 0 else np.swapaxes(world[:, a], -1, -2) @ world[:, j] for j, a in pairs]
    return matrix_to_quat(np.stack(out, axis=1))


def source_members(fr: FrameRetargeter) -> dict[str, list[tuple[int, int]]]:
    """Per BN joint of `GROUPS`, the client (joint, anchor) pairs its rotation is compared with:
    the mapped client joint and the unmapped joints inside the segment the BN bone takes (e.g.
    Xia's LowerBack inside hips -> spine, its Neck inside chest -> neck), whose rotations move
    that segment too, each relative to the mapped joint's nearest mapped ancestor (the client
    chain may hold more joints than BN's; the relative rotation spans the same body part)."""
    hr = fr.humanoid
    parents = hr.skeleton.parents
    client_of = {b: hr.roles[r] for r, b in bn_joints_of(hr.roles).items()}
    mapped = set(client_of.values())
    segs = bn_segments(hr.roles)
    out = {}
    for n in joint_names():
        j = client_of[n]
        a = int(parents[j])
        while a >= 0 and a not in mapped:
            a = int(parents[a])
        inside = {int(parents[k]) for k, _ in _path_terms(hr.skeleton, *(hr.roles[r] for r in segs[n]))}
        out[n] = [(j, a)] + [(k, a) for k in sorted(inside - mapped)]
    return out


def styled(rotations: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """BN local rotations (F, 22, 4) with `STYLE_OFFSETS` applied after each joint's own rotation."""
    out = rotations.copy()
    for n, v in STYLE_OFFSETS.items():
        j = names.index(n)
        out[:, j] = quat_mul(out[:, j], quat_exp(np.asarray(v, float)))
    return out


def clip_jitter(motion: Motion, fps: float, fr: FrameRetargeter | None = None) -> dict[str, np.ndarray]:
    """Per BN joint of `GROUPS` (order `joint_names()`): p99 acceleration of the source ("src"),
    the retargeted BN motion ("bn") and a styled BN frame mapped back onto the client ("back"),
    each (K,) degrees per frame squared, the motion taken at `fps` (slerp, as the service does)."""
    src = resample(motion, fps)
    fr = fr if fr is not None else FrameRetargeter(motion.skeleton)
    hr, sk = fr.humanoid, fr.rig.skeleton
    names = joint_names()
    members = source_members(fr)
    pairs = [pair for n in names for pair in members[n]]
    hips_t, bn = fr.to_model(src.translations[:, hr.translated], src.rotations)
    _, back = fr.to_source(hips_t, styled(bn, sk.names), src.rotations)

    def p99(rel: np.ndarray) -> np.ndarray:
        return np.percentile(rotation_acceleration(rel), 99, axis=0)

    def worst_member(rotations: np.ndarray) -> np.ndarray:
        acc, at, out = p99(relative_rotations(rotations, src.skeleton.parents, pairs)), 0, []
        for n in names:
            out.append(acc[at : at + len(members[n])].max())
            at += len(members[n])
        return np.array(out)

    return {
        "src": worst_member(src.rotations),
        "bn": p99(bn[:, [sk.index(n) for n in names]]),
        "back": worst_member(back),
    }


def joint_names() -> list[str]:
    return [n for g in GROUPS.values() for n in g]


def group_ratios(jitter: dict[str, np.ndarray], key: str = "bn") -> dict[str, float]:
    """Per group: its worst joint's p99 acceleration over the source's worst joint of the group.
    Per group, not per joint: a segment the client spans with several joints may spread its
    motion differently over them than BN's (e.g. BN's Chest takes the shoulder line, which CMU
    moves with its collars), but a flip shows in the group's worst joint either way."""
    names = joint_names()
    out = {}
    for g, joints in GROUPS.items():
        idx = [names.index(n) for n in joints]
        out[g] = float(np.max(jitter[key][idx]) / max(float(np.max(jitter["src"][idx])), 1e-6))
    return out


def _clips() -> list[tuple[str, Motion]]:
    from models.data import build_index, load_motion

    return [(f"{c.dataset}/{c.name}", load_motion(c)) for c in build_index(["cmu", "xia"])]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fps", type=float, nargs="+", default=[30.0, 120.0])
    ap.add_argument("--joints", action="store_true", help="print every joint, not only the groups")
    args = ap.parse_args(argv)
    names = joint_names()
    worst = 0.0
    for key, motion in _clips():
        fr = FrameRetargeter(motion.skeleton)
        for fps in args.fps:
            j = clip_jitter(motion, fps, fr)
            r, rb = group_ratios(j), group_ratios(j, "back")
            worst = max(worst, *r.values(), *rb.values())
            cells = " ".join(f"{g} {r[g]:5.2f}/{rb[g]:5.2f}" for g in GROUPS)
            print(f"{key:32s} {fps:5.0f} fps  ratio bn/back: {cells}")
            if args.joints:
                for i, n in enumerate(names):
                    print(f"    {n:12s} src {j['src'][i]:7.2f}  bn {j['bn'][i]:7.2f}  back {j['back'][i]:7.2f}")
    print(f"worst group ratio {worst:.2f} (bound {BOUND})")
    return 0 if worst <= BOUND else 1


if __name__ == "__main__":
    raise SystemExit(main())
