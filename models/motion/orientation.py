"""Which way the head, hands and feet face: oriented solids for renders, from joint rotations.

A stick figure hides a head turned backwards or a twisted wrist. A part's axes at frame t are
R_world(t) @ A, A calibrated once per skeleton from a reference pose (never per motion on a known
rig, or a head turned from frame 0 would look right).

Part frames (columns of A, right-handed, z = x × y):
  head       x face forward (the nose), y up
  hand       x wrist to fingers, y toward the thumb (z: the left palm's normal, the right's back)
  foot, toe  x forward (ankle to toe, level in the reference pose), y up (the top face)
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cache

import numpy as np

from .assets import bandai_namco_pose, cmu_pose
from .features import UP, body_joint, facing_yaw, left_leg_length
from .humanoid import match_roles, split_name
from .rotations import matrix_to_quat, quat_to_matrix
from .skeleton import Motion, Skeleton

_LEFT = re.compile(r"(_L$|^Left|^L(?=[A-Z])|^lhand$)")
_RIGHT = re.compile(r"(_R$|^Right|^R(?=[A-Z])|^rhand$)")
_HEAD = re.compile(r"head", re.I)
_HAND = re.compile(r"hand|wrist", re.I)
_DIGIT = re.compile(r"finger|thumb|index|middle|ring|pinky|little", re.I)
_FOOT = re.compile(r"foot|ankle", re.I)
_TOE = re.compile(r"toe", re.I)

# Quads of a hexahedron whose corner k sits at (x, y, z) = (bit 2, bit 1, bit 0) of k, i.e. corner
# ix * 4 + iy * 2 + iz; each quad runs counter-clockwise seen from outside: x-, x+, y-, y+, z-, z+.
FACES = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])


def joint_sides(skeleton: Skeleton) -> np.ndarray:
    """+1 left, -1 right, 0 centre line, by name (`humanoid.split_name`, else CMU's `LHipJoint`)."""

    def side(name: str) -> int:
        marker = split_name(name)[0]
        if marker:
            return 1 if marker == "l" else -1
        return 1 if _LEFT.search(name) else -1 if _RIGHT.search(name) else 0

    return np.array([side(n) for n in skeleton.names], int)


def _first(names: tuple[str, ...], ok: Callable[[int, str], bool]) -> int | None:
    """The first joint (hierarchy order, so the one nearest the root) for which ok(index, name)."""
    return next((j for j, n in enumerate(names) if ok(j, n)), None)


# humanoid role -> part drawn as a solid (the roles' names, but `toe` for `toes`)
_ROLE_PARTS = {
    r: r.replace("toes", "toe") for r in ("head", "hand_l", "hand_r", "foot_l", "foot_r", "toes_l", "toes_r")
}


def find_parts(skeleton: Skeleton) -> dict[str, int]:
    """Joint of each part (`head`, `hand_l`, ...) by role, `features.body_joint`, then by name."""
    _, roles = match_roles(skeleton)
    found = {part: roles[role] for role, part in _ROLE_PARTS.items() if role in roles}
    return found | {p: j for p, j in _parts_by_pattern(skeleton).items() if p not in found}


def _parts_by_pattern(skeleton: Skeleton) -> dict[str, int]:
    names, sides = skeleton.names, joint_sides(skeleton)
    out: dict[str, int] = {}
    head = _first(names, lambda j, n: n.lower() == "head")
    head = head if head is not None else _first(names, lambda j, n: sides[j] == 0 and bool(_HEAD.search(n)))
    if head is not None:
        out["head"] = head
    for tag, side in (("l", 1), ("r", -1)):

        def is_hand(j: int, n: str, side: int = side) -> bool:
            return sides[j] == side and bool(_HAND.search(n)) and not _DIGIT.search(n)

        def found(pattern: re.Pattern[str], side: int = side) -> int | None:
            return _first(names, lambda j, n: sides[j] == side and bool(pattern.search(n)))

        hand = _first(names, is_hand)
        if hand is not None:
            out[f"hand_{tag}"] = hand
        for part, feature, pattern in (("foot", "ankle", _FOOT), ("toe", "toe", _TOE)):
            try:
                joint: int | None = body_joint(skeleton, f"{feature}_{tag}")
            except KeyError:
                joint = found(pattern)
            if joint is not None:
                out[f"{part}_{tag}"] = joint
    return out


def _frame(x: np.ndarray, y_hint: np.ndarray, fallback: np.ndarray = UP) -> np.ndarray:
    """(3, 3) right-handed axes: x along `x`, y along `y_hint` made perpendicular (or `fallback`)."""
    x = x / np.linalg.norm(x)
    for hint in (y_hint, fallback):
        y = hint - (hint @ x) * x
        if np.linalg.norm(y) > 0.1 * np.linalg.norm(hint):
            y = y / np.linalg.norm(y)
            return np.stack([x, y, np.cross(x, y)], axis=-1)
    raise ValueError("hint and fallback are both parallel to the axis")


def _level(v: np.ndarray, default: np.ndarray) -> np.ndarray:
    """`v` projected onto the ground plane, or `default` where it is (nearly) vertical."""
    flat = v * np.array([1.0, 0.0, 1.0])
    return flat if np.linalg.norm(flat) > 1e-3 * max(float(np.linalg.norm(v)), 1e-12) else default


def body_forward(positions: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """(3,) level unit vector the pose (J, 3) faces (else +Z)."""
    try:
        yaw = float(facing_yaw(positions, skeleton))
    except KeyError:
        _, roles = match_roles(skeleton)
        if not all(r in roles for r in ("upperleg_l", "upperleg_r", "upperarm_l", "upperarm_r")):
            return np.array([0.0, 0.0, 1.0])
        left = (
            positions[roles["upperleg_l"]]
            - positions[roles["upperleg_r"]]
            + positions[roles["upperarm_l"]]
            - positions[roles["upperarm_r"]]
        )
        forward = np.cross(left, UP)
        yaw = float(np.arctan2(forward[0], forward[2]))
    return np.array([np.sin(yaw), 0.0, np.cos(yaw)])


def part_axes(reference: Motion, frame: int = 0) -> dict[str, tuple[str, np.ndarray]]:
    """Calibration from one pose: part -> (joint name, (3, 3) axes in the joint's frame)."""
    sk = reference.skeleton
    g_rot, g_pos = reference.slice(frame, frame + 1).global_transforms()
    rot, pos = g_rot[0], g_pos[0]
    forward = body_forward(pos, sk)
    parts = find_parts(sk)
    world: dict[str, np.ndarray] = {}
    if "head" in parts:
        world["head"] = _frame(forward, UP)
    for tag in "lr":
        if f"hand_{tag}" in parts:
            hand = parts[f"hand_{tag}"]
            elbow = int(sk.parents[hand])
            while elbow >= 0 and np.linalg.norm(pos[hand] - pos[elbow]) < 1e-6:  # skip zero-length bones
                elbow = int(sk.parents[elbow])
            along = pos[hand] - pos[elbow] if elbow >= 0 else -UP
            world[f"hand_{tag}"] = _frame(along, forward)
        if f"foot_{tag}" in parts:
            toe = parts.get(f"toe_{tag}")
            ahead = _level(pos[toe] - pos[parts[f"foot_{tag}"]], forward) if toe is not None else forward
            world[f"foot_{tag}"] = _frame(ahead, UP)
            if toe is not None:
                world[f"toe_{tag}"] = world[f"foot_{tag}"]
    return {p: (sk.names[parts[p]], quat_to_matrix(rot[parts[p]]).T @ axes) for p, axes in world.items()}


@dataclass(frozen=True)
class Solid:
    """One drawn block: a hexahedron fixed in a part's frame, which is fixed in a joint's frame."""

    part: str  # head, nose, hand_l, thumb_l, foot_l, toe_l, ...
    joint: int
    axes: np.ndarray  # (3, 3) the part frame's axes in the joint's local frame (columns)
    corners: np.ndarray  # (8, 3) in the part frame, skeleton units; corner ix * 4 + iy * 2 + iz
    side: int  # +1 left, -1 right, 0 centre
    mark: bool  # the nose and the thumb stubs: drawn in a contrasting colour


def _block(
    x: tuple[float, float], y_back: tuple[float, float], y_front: tuple[float, float], z: tuple[float, float]
) -> np.ndarray:
    """(8, 3) corners of a box (or a wedge, where `y_back` and `y_front` differ) along x."""
    return np.array([[x[ix], (y_back, y_front)[ix][iy], z[iz]] for ix in (0, 1) for iy in (0, 1) for iz in (0, 1)])


def _size(skeleton: Skeleton) -> float:
    """Left leg length at rest, or half the rest pose's extent without legs."""
    try:
        return left_leg_length(skeleton)
    except KeyError:
        rest = skeleton.rest_positions()
        return 0.5 * float(np.ptp(rest, axis=0).max()) or 1.0


def _end_length(skeleton: Skeleton, joint: int) -> float:
    end = skeleton.end_sites[joint]
    return 0.0 if np.isnan(end).any() else float(np.linalg.norm(end))


def build_solids(skeleton: Skeleton, axes: dict[str, tuple[str, np.ndarray]]) -> tuple[Solid, ...]:
    """The blocks for a skeleton, sized by leg length or by its End Sites where it has them."""
    L = _size(skeleton)
    names = skeleton.names
    out: list[Solid] = []

    def add(part: str, joint: int, a: np.ndarray, corners: np.ndarray, side: int, mark: bool = False) -> None:
        out.append(Solid(part, joint, a, corners, side, mark))

    if "head" in axes and axes["head"][0] in names:
        j, a = names.index(axes["head"][0]), axes["head"][1]
        end = _end_length(skeleton, j)
        top = end + 0.01 * L if end > 0.05 * L else 0.22 * L
        h, bottom = 0.25 * L, top - 0.25 * L
        add("head", j, a, _block((-0.1 * L, 0.1 * L), (bottom, top), (bottom, top), (-0.08 * L, 0.08 * L)), 0)
        nose = ((0.1 * L, 0.2 * L), (bottom + 0.28 * h, bottom + 0.52 * h), (bottom + 0.3 * h, bottom + 0.38 * h))
        add("nose", j, a, _block(*nose, (-0.025 * L, 0.025 * L)), 0, mark=True)
    for tag, side in (("l", 1), ("r", -1)):
        if f"hand_{tag}" in axes and axes[f"hand_{tag}"][0] in names:
            j, a = names.index(axes[f"hand_{tag}"][0]), axes[f"hand_{tag}"][1]
            hand = _block((0.0, 0.2 * L), (-0.05 * L, 0.05 * L), (-0.05 * L, 0.05 * L), (-0.018 * L, 0.018 * L))
            thumb = _block((0.02 * L, 0.1 * L), (0.03 * L, 0.07 * L), (0.07 * L, 0.12 * L), (-0.016 * L, 0.016 * L))
            add(f"hand_{tag}", j, a, hand, side)
            add(f"thumb_{tag}", j, a, thumb, side, mark=True)
        if f"foot_{tag}" in axes and axes[f"foot_{tag}"][0] in names:
            j, a = names.index(axes[f"foot_{tag}"][0]), axes[f"foot_{tag}"][1]
            toe = (
                names.index(axes[f"toe_{tag}"][0]) if f"toe_{tag}" in axes and axes[f"toe_{tag}"][0] in names else None
            )
            # the toe joint in the foot's part frame (pose-independent: it is the bone's offset)
            d = a.T @ skeleton.offsets[toe] if toe is not None else np.array([0.12 * L, -0.09 * L, 0.0])
            sole = d[1] - 0.05 * L
            foot = _block((-0.07 * L, d[0]), (sole, 0.02 * L), (sole, d[1] + 0.035 * L), (-0.05 * L, 0.05 * L))
            add(f"foot_{tag}", j, a, foot, side)
            if toe is not None:
                end = _end_length(skeleton, toe)
                length = end if end > 0.03 * L else 0.08 * L
                block = _block((0.0, length), (-0.05 * L, 0.035 * L), (-0.05 * L, 0.0), (-0.045 * L, 0.045 * L))
                add(f"toe_{tag}", toe, axes[f"toe_{tag}"][1], block, side)
    return tuple(out)


def _chains(skeleton: Skeleton, joints: Iterable[int]) -> list[int]:
    """The joints and all their ancestors."""
    out: set[int] = set()
    for j in joints:
        while j >= 0 and j not in out:
            out.add(int(j))
            j = int(skeleton.parents[j])
    return sorted(out)


def same_rig(reference: Skeleton, skeleton: Skeleton) -> bool:
    """Whether `skeleton` can borrow `reference`'s calibration (same joints, parents, bone directions)."""
    scale = float(np.abs(reference.offsets).max()) or 1.0
    scale_b = float(np.abs(skeleton.offsets).max()) or 1.0
    for j in _chains(reference, find_parts(reference).values()):
        name, parent = reference.names[j], reference.parents[j]
        if name not in skeleton.names:
            return False
        k = skeleton.names.index(name)
        p = skeleton.parents[k]
        if (parent < 0) != (p < 0) or (parent >= 0 and reference.names[parent] != skeleton.names[p]):
            return False
        if parent < 0:
            continue  # the root's offset is its position
        a, b = reference.offsets[j] / scale, skeleton.offsets[k] / scale_b
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if max(na, nb) > 0.02 and not (min(na, nb) > 0 and a @ b / (na * nb) > 0.9):
            return False
    return True


@cache
def _asset_axes(which: str) -> dict[str, tuple[str, np.ndarray]]:
    return part_axes(bandai_namco_pose() if which == "bandai_namco" else cmu_pose())


def reference_rig(skeleton: Skeleton) -> str | None:
    """The committed reference pose (`bandai_namco`, `cmu`) calibrating this skeleton, if any."""
    for which, pose in (("bandai_namco", bandai_namco_pose()), ("cmu", cmu_pose())):
        if same_rig(pose.skeleton, skeleton):
            return which
    return None


_RIGS: dict[tuple, tuple[Solid, ...]] = {}


def rig(motion: Motion) -> tuple[Solid, ...]:
    """The solids for a motion's skeleton, from its rig's reference pose (cached) or its first frame."""
    sk = motion.skeleton
    key = (sk.names, sk.parents.tobytes(), np.round(sk.offsets, 6).tobytes(), np.nan_to_num(sk.end_sites).tobytes())
    if key not in _RIGS:
        which = reference_rig(sk)
        if which is None:
            return build_solids(sk, part_axes(motion))
        _RIGS[key] = build_solids(sk, _asset_axes(which))
    return _RIGS[key]


def solid_corners(global_rotations: np.ndarray, global_positions: np.ndarray, solids: tuple[Solid, ...]) -> np.ndarray:
    """(..., S, 8, 3) world corners of every solid from world rotations (..., J, 4) and positions (..., J, 3)."""
    joints = np.array([s.joint for s in solids], int)
    frames = quat_to_matrix(global_rotations[..., joints, :]) @ np.stack([s.axes for s in solids])  # (..., S, 3, 3)
    local = np.stack([s.corners for s in solids])  # (S, 8, 3)
    return global_positions[..., joints, None, :] + np.einsum("...sab,skb->...ska", frames, local)


def face_normals(corners: np.ndarray) -> np.ndarray:
    """(..., 6, 3) outward unit normals of each solid's quads (`FACES`) from corners (..., 8, 3)."""
    quads = corners[..., FACES, :]  # (..., 6, 4, 3)
    n = np.cross(quads[..., 2, :] - quads[..., 0, :], quads[..., 3, :] - quads[..., 1, :])
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def solids_json(solids: tuple[Solid, ...]) -> list[dict]:
    """The solids for the browser viewer: joint, part frame quaternion (xyzw), part-frame corners."""
    return [
        {
            "part": s.part,
            "joint": s.joint,
            "rotation": np.round(matrix_to_quat(s.axes), 6).tolist(),
            "corners": np.round(s.corners, 4).tolist(),
            "side": s.side,
            "mark": s.mark,
        }
        for s in solids
    ]
