"""Any humanoid rig: which joint plays which body role, and how the rig sits in the world.

Rigs are known by joint *names* and *hierarchy* only, never by rest pose, so T-pose, A-pose or
BN's zero pose map alike. Roles (`ROLES`, `REQUIRED`): hips, up to four spine joints, neck, head,
and per side clavicle to hand, upper leg to toes. `match_roles`: a `joint_map`, then an exact
preset table, then aliases without side markers and prefixes, ambiguous names by their order
along the limb. `check_topology` names every fault at once; `HumanoidRig` holds the world (up
axis, handedness, units, the joint a frame's `root` moves).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from . import bvh as bvhio
from .bn_skeleton import BN_JOINTS
from .humanoid_presets import PRESETS, preset_skeleton
from .rotations import matrix_to_quat, quat_to_matrix
from .skeleton import Motion, Skeleton, depths, skeleton_from_bvh

SIDED_PARTS = ("clavicle", "upperarm", "lowerarm", "hand", "upperleg", "lowerleg", "foot", "toes")
ARM, LEG = SIDED_PARTS[:4], SIDED_PARTS[4:]
SPINE = ("spine1", "spine2", "spine3", "spine4")
ROLES = ("hips", *SPINE, "neck", "head", *(f"{p}_{s}" for s in "lr" for p in SIDED_PARTS))
REQUIRED = ("hips", "spine1", "head", *(f"{p}_{s}" for s in "lr" for p in SIDED_PARTS[1:-1]))

# BN joint -> the role of the client joint at the same body position
BN_ROLES = {
    "Hips": "hips",
    "Neck": "neck",
    "Head": "head",
    **{
        f"{bn}_{s.upper()}": f"{p}_{s}"
        for s in "lr"
        for bn, p in (
            ("Shoulder", "clavicle"),
            ("UpperArm", "upperarm"),
            ("LowerArm", "lowerarm"),
            ("Hand", "hand"),
            ("UpperLeg", "upperleg"),
            ("LowerLeg", "lowerleg"),
            ("Foot", "foot"),
            ("Toes", "toes"),
        )
    },
}

# BN joint (after joint_Root) -> CMU joint at the same body position, for the two CMU namings.
_CGSPEED = dict(
    zip(
        BN_JOINTS[1:],
        "Hips Spine Spine1 Neck1 Head LeftShoulder LeftArm LeftForeArm LeftHand RightShoulder RightArm RightForeArm "
        "RightHand LeftUpLeg LeftLeg LeftFoot LeftToeBase RightUpLeg RightLeg RightFoot RightToeBase".split(),
        strict=True,
    )
)
_BVH11 = dict(
    zip(
        BN_JOINTS[1:],
        "Hips Chest Chest2 Neck Head LeftCollar LeftShoulder LeftElbow LeftWrist RightCollar RightShoulder RightElbow "
        "RightWrist LeftHip LeftKnee LeftAnkle LeftToe RightHip RightKnee RightAnkle RightToe".split(),
        strict=True,
    )
)
CMU_TO_BN = {"cmu": _CGSPEED, "cmu-bvh11": _BVH11}  # by `rig_kind`: Xia uses the first, 100STYLE the second


def _bn_table(bn_to_joint: dict[str, str]) -> dict[str, str]:
    """{role: joint} from a {BN joint: joint} table (BN Spine / Chest are spine1 / spine2)."""
    out = {BN_ROLES[b]: j for b, j in bn_to_joint.items() if b in BN_ROLES}
    out["spine1"], out["spine2"] = bn_to_joint["Spine"], bn_to_joint["Chest"]
    return out


# exact tables tried before aliases: preset name -> {role: joint name}
TABLES: dict[str, dict[str, str]] = {
    "bandai-namco": _bn_table({b: b for b in BN_JOINTS}),
    "cmu": _bn_table(_CGSPEED),
    "cmu-bvh11": _bn_table(_BVH11),
    **{name: p.role_names() for name, p in PRESETS.items()},
}
PRESET_NAMES = ("bandai-namco", "cmu", *PRESETS)

# name aliases (side marker removed, lower case, separators dropped) -> candidate parts
_HIPS, _HEAD = {"hips", "hip", "pelvis"}, {"head"}
_NECK = re.compile(r"^neck\d*$")
_PART_ALIASES = {
    "clavicle": {"clavicle", "collar", "collarbone", "shoulder"},
    "upperarm": {"upperarm", "arm", "uparm", "shoulder", "humerus"},
    "lowerarm": {"lowerarm", "forearm", "elbow", "lowarm"},
    "hand": {"hand", "wrist"},
    "upperleg": {"upperleg", "upleg", "thigh", "hip", "femur"},
    "lowerleg": {"lowerleg", "leg", "calf", "knee", "shin", "lowleg"},
    "foot": {"foot", "ankle"},
    "toes": {"toes", "toe", "toebase", "ball", "foot", "toe0"},
}
_DROP = {"mixamorig", "j", "bip", "c"}
_TOKENS = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")
UNITS_CM = {"m": 100.0, "dm": 10.0, "cm": 1.0, "mm": 0.1, "in": 2.54}
TYPICAL_LEG_CM = 85.0  # thigh + shin of an adult, for reading units off a rig


class RigError(ValueError):
    """A rig that cannot be mapped; `code` is the protocol's error code, `missing` all roles at fault."""

    def __init__(self, code: str, message: str, missing: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.code, self.message, self.missing = code, message, tuple(missing)


def split_name(name: str) -> tuple[str | None, str]:
    """(side 'l' / 'r' / None, base) of a joint name: 'mixamorig:LeftUpLeg' -> ('l', 'upleg'),
    'upperarm_twist_01_r' -> ('r', 'upperarmtwist01'), 'Hand.L' -> ('l', 'hand')."""
    core = name.rsplit(":", 1)[-1]
    tokens = [t.lower() for t in _TOKENS.findall(core)]
    while tokens and (tokens[0] in _DROP or (tokens[0] == "bip" and len(tokens) > 1)):
        tokens = tokens[2:] if tokens[0] == "bip" and len(tokens) > 1 and tokens[1].isdigit() else tokens[1:]
    sides = [i for i, t in enumerate(tokens) if t in ("l", "left", "r", "right")]
    side = None
    if len(sides) == 1:
        i = sides[0]
        side = tokens[i][0]
        tokens = tokens[:i] + tokens[i + 1 :]
    return side, "".join(t for t in tokens if t not in ("c",) or len(tokens) == 1)


def is_ancestor(parents: np.ndarray, a: int, b: int) -> bool:
    """a is b or one of b's ancestors."""
    while b >= 0:
        if b == a:
            return True
        b = int(parents[b])
    return False


def path_length(skeleton: Skeleton, a: int, b: int) -> float:
    """Sum of bone lengths from ancestor a down to b (its length in any pose if the joints are in line)."""
    total = 0.0
    while b != a and b >= 0:
        total += float(np.linalg.norm(skeleton.offsets[b]))
        b = int(skeleton.parents[b])
    return total


def _lookup(skeleton: Skeleton) -> dict[str, int]:
    """Joint name (case-insensitive, any 'prefix:' dropped) -> index."""
    out: dict[str, int] = {}
    for j, n in enumerate(skeleton.names):
        out.setdefault(n.lower(), j)
        out.setdefault(n.rsplit(":", 1)[-1].lower(), j)
    return out


def _from_table(skeleton: Skeleton, excluded: set[int]) -> tuple[str | None, dict[str, int]]:
    """The preset table with every required name present (the one covering most roles)."""
    names = _lookup(skeleton)
    best: tuple[str | None, dict[str, int]] = (None, {})
    score = (0, 0)
    for preset, table in TABLES.items():
        found = {
            r: names[n.lower()] for r, n in table.items() if n.lower() in names and names[n.lower()] not in excluded
        }
        exact = sum(skeleton.names[j].rsplit(":", 1)[-1] == table[r] for r, j in found.items())
        if all(r in found for r in REQUIRED) and (len(found), exact) > score:
            best, score = (preset, found), (len(found), exact)
    return best


def _assign_chain(
    joints: list[int], candidates: list[set[str]], parts: tuple[str, ...], required: set[str]
) -> dict[str, int]:
    """Roles `parts` onto joints in order along the chain, required ones first (a small DP)."""
    best: dict[tuple[int, int], tuple[int, dict[str, int]]] = {}

    def solve(i: int, k: int) -> tuple[int, dict[str, int]]:
        if i == len(joints) or k == len(parts):
            return 0, {}
        if (i, k) in best:
            return best[(i, k)]
        result = solve(i + 1, k)  # joint i plays no role
        for kk in range(k, len(parts)):
            if parts[kk] in candidates[i]:
                score, rest = solve(i + 1, kk + 1)
                score += 10 if parts[kk] in required else 1
                if score >= result[0]:
                    result = (score, {parts[kk]: joints[i], **rest})
        best[(i, k)] = result
        return result

    return solve(0, 0)[1]


def _from_aliases(skeleton: Skeleton, fixed: dict[str, int], excluded: set[int]) -> dict[str, int]:
    parents, depth = skeleton.parents, depths(skeleton.parents)
    split = [split_name(n) for n in skeleton.names]
    free = [j for j in range(skeleton.num_joints) if j not in excluded and j not in fixed.values()]
    roles = dict(fixed)

    def pick(match, key) -> int | None:
        hits = [j for j in free if match(*split[j])]
        return min(hits, key=key) if hits else None

    if "hips" not in roles:
        j = pick(lambda s, b: s is None and b in _HIPS, lambda j: depth[j])
        if j is not None:
            roles["hips"] = j
    hips = roles.get("hips")
    below = lambda j: hips is not None and is_ancestor(parents, hips, j) and j != hips
    if "head" not in roles:
        j = pick(lambda s, b: s is None and b in _HEAD, lambda j: (not below(j), depth[j]))
        if j is not None:
            roles["head"] = j
    if "neck" not in roles and "head" in roles:
        j = pick(
            lambda s, b: s is None and bool(_NECK.match(b)),
            lambda j: (not is_ancestor(parents, j, roles["head"]), -depth[j]),
        )
        if j is not None and is_ancestor(parents, j, roles["head"]):
            roles["neck"] = j
    for side in "lr":
        for parts in (ARM, LEG):
            want = [f"{p}_{side}" for p in parts]
            todo = tuple(r for r in want if r not in roles)
            chain = sorted(
                (
                    j
                    for j in free
                    if split[j][0] == side
                    and (hips is None or below(j))
                    and any(split[j][1] in _PART_ALIASES[r[:-2]] for r in todo)
                ),
                key=lambda j: depth[j],
            )
            cands = [{r for r in todo if split[j][1] in _PART_ALIASES[r[:-2]]} for j in chain]
            roles.update(_assign_chain(chain, cands, todo, set(REQUIRED)))
    return roles


def _spine_chain(skeleton: Skeleton, roles: dict[str, int]) -> list[int]:
    """Joints strictly between the hips and the neck (or head), bottom-up, with length or arms."""
    hips = roles.get("hips")
    top = roles.get("neck", roles.get("head"))
    if hips is None or top is None or not is_ancestor(skeleton.parents, hips, top):
        return []
    arms = [roles[r] for r in ("clavicle_l", "upperarm_l", "clavicle_r", "upperarm_r") if r in roles]
    chain = []
    j = int(skeleton.parents[top])
    while j != hips and j >= 0:
        chain.append(j)
        j = int(skeleton.parents[j])
    chain = chain[::-1]
    necks = {
        j for j in chain if _NECK.match(split_name(skeleton.names[j])[1]) and split_name(skeleton.names[j])[0] is None
    }
    carries = {
        j
        for j in chain
        if any(
            is_ancestor(skeleton.parents, j, a)
            and not any(
                is_ancestor(skeleton.parents, c, a) for c in chain if c != j and is_ancestor(skeleton.parents, j, c)
            )
            for a in arms
        )
    }
    return [
        j
        for j in chain
        if (j not in necks or j in carries) and (np.linalg.norm(skeleton.offsets[j]) > 1e-9 or j in carries)
    ]


def match_roles(
    skeleton: Skeleton, joint_map: dict[str, str | None] | None = None
) -> tuple[str | None, dict[str, int]]:
    """(matched preset or None, {role: joint}); `joint_map` {joint: role or None} overrides."""
    fixed: dict[str, int] = {}
    excluded: set[int] = set()
    names = _lookup(skeleton)
    unknown_joints = [j for j in (joint_map or {}) if j.lower() not in names]
    unknown_roles = [r for r in (joint_map or {}).values() if r is not None and r not in ROLES]
    problems = []
    if unknown_joints:
        problems.append(f"joint_map names joints the skeleton lacks: {', '.join(unknown_joints)}")
    if unknown_roles:
        problems.append(f"joint_map names unknown roles: {', '.join(unknown_roles)} (roles: {', '.join(ROLES)})")
    if problems:
        raise RigError("bad_joint_map", "; ".join(problems), tuple(unknown_joints + unknown_roles))
    for joint, role in (joint_map or {}).items():
        j = names[joint.lower()]
        if role is None:
            excluded.add(j)
        elif role in fixed and fixed[role] != j:
            raise RigError("bad_joint_map", f"joint_map gives role {role} to two joints", (role,))
        else:
            fixed[role] = j
    preset, roles = _from_table(skeleton, excluded | set(fixed.values()))
    if preset is None:
        roles = _from_aliases(skeleton, fixed, excluded)
    else:
        roles = {r: j for r, j in roles.items() if r not in fixed} | fixed
    if not any(r in fixed for r in SPINE) and (preset is None or "spine1" not in roles):
        for r in SPINE:
            roles.pop(r, None)
        chain = _spine_chain(skeleton, roles)
        keep = chain if len(chain) <= 4 else chain[:3] + chain[-1:]
        roles.update({SPINE[k]: j for k, j in enumerate(keep)})
    taken: dict = {}
    for r, j in list(roles.items()):
        if j in taken and r not in fixed:
            del roles[r]
        taken.setdefault(j, r)
    return preset, {r: roles[r] for r in ROLES if r in roles}


def rig_kind(rig: Skeleton | HumanoidRig) -> str:
    """A skeleton's preset by joint names ('bandai-namco', 'cmu', 'mixamo', ...), else 'humanoid'."""
    preset = rig.preset if isinstance(rig, HumanoidRig) else match_roles(rig)[0]
    return preset or "humanoid"


def chest_role(roles: dict[str, int] | set[str]) -> str:
    """The top spine role (the chest)."""
    return [r for r in SPINE if r in roles][-1]


def bn_segments(roles: dict[str, int] | set[str]) -> dict[str, tuple[str, str]]:
    """BN joint -> (role, role): the client segment its bone follows (optional roles fall back)."""
    chest = chest_role(roles)
    lower_spine = "spine1" if chest != "spine1" else "hips"
    neck = "neck" if "neck" in roles else chest
    out = {
        "Hips": ("hips", "spine1"),
        "Spine": (lower_spine, chest),
        "Chest": (chest, "neck" if "neck" in roles else "head"),
        "Neck": (neck, "head"),
    }
    for s in "lr":
        S = s.upper()
        out[f"Shoulder_{S}"] = (f"clavicle_{s}" if f"clavicle_{s}" in roles else chest, f"upperarm_{s}")
        out[f"UpperArm_{S}"] = (f"upperarm_{s}", f"lowerarm_{s}")
        out[f"LowerArm_{S}"] = (f"lowerarm_{s}", f"hand_{s}")
        out[f"UpperLeg_{S}"] = (f"upperleg_{s}", f"lowerleg_{s}")
        out[f"LowerLeg_{S}"] = (f"lowerleg_{s}", f"foot_{s}")
        if f"toes_{s}" in roles:
            out[f"Foot_{S}"] = (f"foot_{s}", f"toes_{s}")
    return out


def bn_joints_of(roles: dict[str, int]) -> dict[str, str]:
    """Role -> BN joint for the client joints that take a BN joint's change on the way back."""
    chest = chest_role(roles)
    out = {BN_ROLES[b] if b in BN_ROLES else b: b for b in BN_ROLES if BN_ROLES[b] in roles}
    out[chest] = "Chest"
    if chest != "spine1":
        out["spine1"] = "Spine"
    return out


def check_topology(skeleton: Skeleton, roles: dict[str, int]) -> None:
    """Raise `RigError` naming every missing role, link out of order and zero-length segment."""
    missing = [r for r in REQUIRED if r not in roles]
    if missing:
        raise RigError(
            "missing_roles",
            f"the skeleton lacks joints for: {', '.join(missing)} (give them in joint_map as {{joint: role}})",
            tuple(missing),
        )
    par = skeleton.parents
    chest = chest_role(roles)
    links = [("hips", "spine1"), *zip(SPINE, SPINE[1:]), (chest, "neck"), ("neck", "head"), (chest, "head")]
    for s in "lr":
        arm = [chest, *(f"{p}_{s}" for p in ARM)]
        leg = ["hips", *(f"{p}_{s}" for p in LEG)]
        links += list(zip(arm, arm[1:])) + list(zip(arm, arm[2:])) + list(zip(leg, leg[1:])) + list(zip(leg, leg[2:]))
    broken = []
    for a, b in links:
        if a in roles and b in roles and (roles[a] == roles[b] or not is_ancestor(par, roles[a], roles[b])):
            broken.append(f"{b} ({skeleton.names[roles[b]]}) is not below {a} ({skeleton.names[roles[a]]})")
    short = (
        []
        if broken
        else [f"{a} -> {b}" for a, b in bn_segments(roles).values() if path_length(skeleton, roles[a], roles[b]) < 1e-9]
    )
    if broken or short:
        raise RigError(
            "bad_topology", "; ".join(broken + [f"zero-length segment {s}" for s in short]), tuple(broken + short)
        )


# --------------------------------------------------------------------------- the world a rig lives in


def axes_matrix(up: str, handedness: str) -> np.ndarray:
    """Client world -> model world (Y up, right-handed); a reflection for left-handed clients."""
    table = {
        ("y", "right"): [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        ("z", "right"): [[1, 0, 0], [0, 0, 1], [0, -1, 0]],
        ("y", "left"): [[1, 0, 0], [0, 1, 0], [0, 0, -1]],
        ("z", "left"): [[1, 0, 0], [0, 0, 1], [0, 1, 0]],
    }
    if (up, handedness) not in table:
        raise RigError(
            "bad_rig", f"up must be 'y' or 'z' and handedness 'right' or 'left' (got {up!r}, {handedness!r})"
        )
    return np.array(table[(up, handedness)], dtype=float)


def detect_up(skeleton: Skeleton, roles: dict[str, int]) -> str | None:
    """'y' or 'z' when the rest pose stands (head above the feet), else None."""
    rest = skeleton.rest_positions()
    v = rest[roles["head"]] - 0.5 * (rest[roles["foot_l"]] + rest[roles["foot_r"]])
    n = np.linalg.norm(v)
    if n < 1e-9:
        return None
    axis = int(np.argmax(np.abs(v)))
    if abs(v[axis]) / n < 0.9 or v[axis] < 0 or axis == 0:
        return None
    return "yz"[axis - 1]


def leg_length(skeleton: Skeleton, roles: dict[str, int] | None = None) -> float:
    """Thigh + shin, mean of both legs: the scale between rigs (`features.left_leg_length` says why)."""
    if roles is None:
        roles = match_roles(skeleton)[1]
    return 0.5 * sum(path_length(skeleton, roles[f"upperleg_{s}"], roles[f"foot_{s}"]) for s in "lr")


def detect_units(leg: float) -> str | None:
    """The unit (m, cm, mm) making the leg a plausible adult's; None if none does (CMU's own unit)."""
    best = min(("m", "cm", "mm"), key=lambda u: abs(np.log(leg * UNITS_CM[u] / TYPICAL_LEG_CM)))
    return best if abs(np.log(leg * UNITS_CM[best] / TYPICAL_LEG_CM)) < np.log(2.5) else None


@dataclass(frozen=True)
class HumanoidRig:
    """A client's rig, matched: its skeleton, the role of each mapped joint and its world."""

    skeleton: Skeleton
    roles: dict[str, int]
    preset: str | None  # the preset table that matched, or None (aliases / joint_map)
    translated: int  # the joint whose translation a frame's `root` is
    up: str
    handedness: str
    units: str | None
    up_detected: bool = False
    joint_map: dict[str, str | None] = field(default_factory=dict)

    @property
    def axes(self) -> np.ndarray:
        return axes_matrix(self.up, self.handedness)

    @property
    def leg_length(self) -> float:
        return leg_length(self.skeleton, self.roles)

    def joint(self, role: str) -> str:
        return self.skeleton.names[self.roles[role]]

    def unmapped(self) -> list[str]:
        used = set(self.roles.values())
        return [n for j, n in enumerate(self.skeleton.names) if j not in used]

    def report(self) -> dict:
        """What the `started` reply and `POST /v1/skeletons` say about the mapping."""
        leg = self.leg_length
        return {
            "preset": self.preset,
            "mapping": {r: self.joint(r) for r in ROLES if r in self.roles},
            "unmapped": self.unmapped(),
            "root_joint": self.skeleton.names[self.translated],
            "up": self.up,
            "up_detected": self.up_detected,
            "handedness": self.handedness,
            "units": self.units,
            "leg_length": round(leg, 6),
        }


def humanoid_rig(
    skeleton: Skeleton,
    joint_map: dict[str, str | None] | None = None,
    up: str | None = None,
    units: str | None = None,
    handedness: str = "right",
    translated: int | None = None,
) -> HumanoidRig:
    """Match and check a skeleton; raises `RigError` (typed, naming everything missing)."""
    preset, roles = match_roles(skeleton, joint_map)
    check_topology(skeleton, roles)
    detected = detect_up(skeleton, roles) if up is None else None
    if units is not None and units not in UNITS_CM:
        raise RigError("bad_rig", f"units must be one of {', '.join(UNITS_CM)} (got {units!r})")
    if up is not None and up not in ("y", "z"):
        raise RigError("bad_rig", f"up must be 'y' or 'z' (got {up!r})")
    hips = roles["hips"]
    if translated is None:
        translated = hips if skeleton.parents[hips] < 0 else 0
    if not is_ancestor(skeleton.parents, translated, hips):
        raise RigError("bad_topology", f"the translated joint {skeleton.names[translated]} is not above the hips")
    axes_matrix(up or detected or "y", handedness)
    return HumanoidRig(
        skeleton,
        roles,
        preset,
        int(translated),
        up or detected or "y",
        handedness,
        units or detect_units(leg_length(skeleton, roles)),
        up is None and detected is not None,
        dict(joint_map or {}),
    )


def rig_from_bvh(text: str, source: str = "bvh_header", **options) -> HumanoidRig:
    """A rig from BVH text; frames move the hips if they have position channels, else the root."""
    header = text.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.0333333\n"
    try:
        parsed = bvhio.parse(header, source)
    except bvhio.BvhError as exc:
        raise RigError("bad_skeleton", str(exc)) from None
    skeleton, _ = skeleton_from_bvh(parsed)
    return humanoid_rig(skeleton, **options, translated=translated_joint(parsed, skeleton, options.get("joint_map")))


def translated_joint(parsed: bvhio.BvhFile, skeleton: Skeleton, joint_map: dict | None = None) -> int | None:
    """The hips if they have position channels (BN animates Hips under a static root), else None."""
    try:
        _, roles = match_roles(skeleton, joint_map)
    except RigError:
        return None
    hips = roles.get("hips")
    return hips if hips is not None and "Xposition" in parsed.joints[hips].channels else None


def restrict(skeleton: Skeleton, joints: list[str]) -> Skeleton:
    """The skeleton on a subset of joints, children of dropped ones hung from the nearest kept one."""
    idx = [skeleton.index(n) for n in joints]
    keep = set(idx)
    rest = skeleton.rest_positions()
    parents, offsets = [], []
    for j in idx:
        p = int(skeleton.parents[j])
        while p >= 0 and p not in keep:
            p = int(skeleton.parents[p])
        parents.append(idx.index(p) if p >= 0 else -1)
        offsets.append(rest[j] - rest[p] if p >= 0 else rest[j])
    return Skeleton(tuple(joints), np.array(parents), np.array(offsets), skeleton.end_sites[idx])


def preset_rig(preset: str, joints: list[str] | None = None, **options) -> HumanoidRig:
    """A preset's reference hierarchy, restricted to `joints` (spelled as the client does)."""
    from .assets import bandai_namco_skeleton, cmu_skeleton

    if preset not in PRESET_NAMES:
        raise RigError("unsupported_skeleton", f"skeleton {preset!r} is not a preset ({', '.join(PRESET_NAMES)})")
    full = {"bandai-namco": bandai_namco_skeleton, "cmu": cmu_skeleton}.get(preset, lambda: preset_skeleton(preset))()
    if joints is not None:
        names = _lookup(full)
        key = [n.lower() if n.lower() in names else n.rsplit(":", 1)[-1].lower() for n in joints]
        unknown = [n for n, k in zip(joints, key) if k not in names]
        if unknown:
            raise RigError(
                "bad_skeleton", f"joints not in the {preset} preset: {', '.join(unknown[:12])}", tuple(unknown)
            )
        if len(set(key)) != len(key):
            raise RigError("bad_skeleton", "joints lists a joint twice")
        order = sorted(range(len(joints)), key=lambda k: names[key[k]])
        base = restrict(full, [full.names[names[key[k]]] for k in order])
        full = Skeleton(tuple(joints[k] for k in order), base.parents, base.offsets, base.end_sites)
    rig = humanoid_rig(full, **options)
    if preset == "bandai-namco":  # BN frames carry the Hips translation (joint_Root is static)
        rig = HumanoidRig(**{**rig.__dict__, "translated": rig.roles["hips"]})
    return rig


def in_model_world(motion: Motion, rig: HumanoidRig) -> Motion:
    """The motion in the model's world (Y up, right-handed, cm), for drawing next to model motions."""
    a = rig.axes
    cm = UNITS_CM.get(rig.units or "", 1.0)
    local = a @ quat_to_matrix(motion.rotations) @ a.T
    sk = motion.skeleton
    skeleton = Skeleton(sk.names, sk.parents, sk.offsets @ a.T * cm, sk.end_sites @ a.T * cm)
    return Motion(skeleton, matrix_to_quat(local), motion.translations @ a.T * cm, motion.fps, motion.euler_orders)
