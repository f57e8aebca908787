"""Naming tables of the humanoid rigs the service knows by name, and their reference hierarchies.

Each preset is one rig family's public joint naming, written from its documented names (no file
of those projects is copied): role -> name (`Preset.roles`) plus the usual extra joints (roots,
end sites, twist bones, fingers). `Preset.skeleton()` builds a reference hierarchy (every rotation
zero = the preset's rest pose: T-pose, or A-pose for the Unreal mannequins) from one template
body in cm. Clients with their own proportions send a BVH header instead.

`{Side}`/`{side}`/`{S}`/`{s}` in a name stand for Left/left/L/l (Right/right/R/r).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np

from .skeleton import Skeleton

# One template body (cm, Y up, facing +Z, its left side at +X), T-pose: role -> rest position.
_TEMPLATE = {
    "hips": (0.0, 95.0, 0.0),
    "spine1": (0.0, 105.0, -1.0),
    "spine2": (0.0, 115.0, -1.5),
    "spine3": (0.0, 125.0, -1.5),
    "spine4": (0.0, 135.0, -1.0),
    "neck": (0.0, 150.0, -1.0),
    "head": (0.0, 160.0, 0.0),
    "clavicle_l": (3.0, 143.0, 0.0),
    "upperarm_l": (17.0, 145.0, -2.0),
    "lowerarm_l": (45.0, 145.0, -2.0),
    "hand_l": (70.0, 145.0, -2.0),
    "upperleg_l": (9.0, 90.0, 0.0),
    "lowerleg_l": (9.0, 50.0, 0.5),
    "foot_l": (9.0, 9.0, -2.0),
    "toes_l": (9.0, 1.0, 12.0),
}
_FINGERS = ("thumb", "index", "middle", "ring", "pinky")
SIDES = {
    "l": {"Side": "Left", "side": "left", "S": "L", "s": "l"},
    "r": {"Side": "Right", "side": "right", "S": "R", "s": "r"},
}


@dataclass(frozen=True)
class Preset:
    """A rig family's naming: roles (sided ones once), spine and neck chains, extra joints."""

    name: str
    roles: dict[str, str]
    spine: tuple[str, ...]  # bottom-up; the last is the chest (clavicles hang from it)
    necks: tuple[str, ...] = ()  # bottom-up; the last plays the `neck` role
    root: str | None = None  # a root joint above the hips, at the floor (Unreal's `root`)
    finger: str | None = None  # finger joint name pattern with {finger} and {i}
    finger_steps: tuple[str, ...] = ("1", "2", "3")  # what {i} becomes along each finger
    finger_names: dict[str, str] = field(default_factory=dict)  # finger -> its name in this rig
    extras: tuple[tuple[str, str, str, float], ...] = ()  # (name, parent, toward joint, fraction of the way)
    a_pose: bool = False
    description: str = ""

    def sided(self, name: str, side: str) -> str:
        return name.format(**SIDES[side])

    def role_names(self) -> dict[str, str]:
        """{role: joint name} for every role this preset has (sides expanded, spine and neck)."""
        out: dict[str, str] = {}
        for role, name in self.roles.items():
            if role.endswith("_x"):
                for side in "lr":
                    out[f"{role[:-2]}_{side}"] = self.sided(name, side)
            else:
                out[role] = name
        n = len(self.spine)
        for k, name in enumerate(self.spine[:3] if n > 4 else self.spine):
            out[f"spine{k + 1}"] = name
        if n > 4:
            out["spine4"] = self.spine[-1]
        if self.necks:
            out["neck"] = self.necks[-1]
        return out

    def skeleton(self) -> Skeleton:
        """The reference hierarchy (BVH convention, every rotation zero = the rest pose)."""
        return _build(self)


def _template_points(a_pose: bool) -> dict[str, np.ndarray]:
    pts = {k: np.array(v) for k, v in _TEMPLATE.items()}
    for key in list(pts):
        if key.endswith("_l"):
            x, y, z = pts[key]
            pts[key[:-1] + "r"] = np.array([-x, y, z])
    if a_pose:  # arms 45 degrees down about the shoulder (Unreal mannequins' rest)
        c, s = np.cos(np.radians(45)), np.sin(np.radians(45))
        for side, sign in (("l", 1.0), ("r", -1.0)):
            pivot = pts[f"upperarm_{side}"]
            for part in ("lowerarm", "hand"):
                d = pts[f"{part}_{side}"] - pivot
                pts[f"{part}_{side}"] = pivot + np.array(
                    [c * d[0] + sign * s * d[1], -sign * s * d[0] + c * d[1], d[2]]
                )
    return pts


def _build(preset: Preset) -> Skeleton:
    pts = _template_points(preset.a_pose)
    names: list[str] = []
    parents: list[int] = []
    where: list[np.ndarray] = []

    def add(name: str, parent: str | None, pos: np.ndarray) -> None:
        names.append(name)
        parents.append(names.index(parent) if parent is not None else -1)
        where.append(np.asarray(pos, dtype=float))

    roles = preset.role_names()
    if preset.root:
        add(preset.root, None, np.zeros(3))
    add(roles["hips"], preset.root, pts["hips"])
    spine_pts = np.linspace(pts["spine1"], pts["spine4"], len(preset.spine))
    below = roles["hips"]
    for name, p in zip(preset.spine, spine_pts):
        add(name, below, p)
        below = name
    chest = below
    if preset.necks:
        for name, p in zip(
            preset.necks,
            np.linspace(pts["spine4"] + 0.6 * (pts["neck"] - pts["spine4"]), pts["neck"], len(preset.necks)),
        ):
            add(name, below, p)
            below = name
    add(roles["head"], below, pts["head"])
    for side in "lr":
        parent = chest
        for part in ("clavicle", "upperarm", "lowerarm", "hand"):
            role = f"{part}_{side}"
            if role in roles:
                add(roles[role], parent, pts[role])
                parent = roles[role]
        if preset.finger:
            hand, fwd = pts[f"hand_{side}"], pts[f"hand_{side}"] - pts[f"lowerarm_{side}"]
            fwd = fwd / np.linalg.norm(fwd)
            for k, finger in enumerate(_FINGERS):
                spread = np.array([0.0, 0.0, 4.0 - 2.0 * k])
                parent = roles[f"hand_{side}"]
                for i, step in enumerate(preset.finger_steps, start=1):
                    own = preset.finger_names.get(finger, finger)
                    name = preset.finger.replace("{finger}", own).replace("{Finger}", own.capitalize())
                    name = preset.sided(name.replace("{i}", step), side)
                    add(name, parent, hand + fwd * (3.0 + 2.5 * i) + spread)
                    parent = name
        parent = roles["hips"]
        for part in ("upperleg", "lowerleg", "foot", "toes"):
            role = f"{part}_{side}"
            if role in roles:
                add(roles[role], parent, pts[role])
                parent = roles[role]
        for name, par, toward, frac in preset.extras:
            name, par = preset.sided(name, side), preset.sided(par, side)
            if par not in names or name in names:
                continue
            a = where[names.index(par)]
            b = where[names.index(preset.sided(toward, side))] if toward else a + np.array([0.0, 10.0, 0.0])
            add(name, par, a + frac * (b - a))
    pos = np.stack(where)
    parent_index = np.array(parents)
    offsets = np.where(parent_index[:, None] >= 0, pos - pos[np.maximum(parent_index, 0)], pos)
    return Skeleton(tuple(names), parent_index, offsets, np.full((len(names), 3), np.nan))


def _roles(hips: str, head: str, limbs: str) -> dict[str, str]:
    """`Preset.roles` from the hips, the head and one row of sided names, clavicle to toes."""
    sided = ("clavicle_x", "upperarm_x", "lowerarm_x", "hand_x", "upperleg_x", "lowerleg_x", "foot_x", "toes_x")
    return {"hips": hips, "head": head, **dict(zip(sided, limbs.split(), strict=True))}


_MIXAMO_ROLES = _roles(
    "Hips", "Head", "{Side}Shoulder {Side}Arm {Side}ForeArm {Side}Hand {Side}UpLeg {Side}Leg {Side}Foot {Side}ToeBase"
)
_UE_ROLES = _roles(
    "pelvis", "head", "clavicle_{s} upperarm_{s} lowerarm_{s} hand_{s} thigh_{s} calf_{s} foot_{s} ball_{s}"
)
_SMPL_ROLES = _roles(
    "pelvis",
    "head",
    "{side}_collar {side}_shoulder {side}_elbow {side}_wrist {side}_hip {side}_knee {side}_ankle {side}_foot",
)

PRESETS: dict[str, Preset] = {
    p.name: p
    for p in (
        Preset(
            "mixamo",
            _MIXAMO_ROLES,
            spine=("Spine", "Spine1", "Spine2"),
            necks=("Neck",),
            finger="{Side}Hand{Finger}{i}",
            finger_steps=("1", "2", "3", "4"),
            extras=(("HeadTop_End", "Head", "", 1.0), ("{Side}Toe_End", "{Side}ToeBase", "", 0.5)),
            description="Adobe Mixamo, with or without the 'mixamorig:' prefix; T-pose",
        ),
        Preset(
            "ue4",
            _UE_ROLES,
            spine=("spine_01", "spine_02", "spine_03"),
            necks=("neck_01",),
            root="root",
            finger="{finger}_{i}_{s}",
            finger_steps=("01", "02", "03"),
            extras=(
                ("upperarm_twist_01_{s}", "upperarm_{s}", "lowerarm_{s}", 0.5),
                ("lowerarm_twist_01_{s}", "lowerarm_{s}", "hand_{s}", 0.5),
                ("thigh_twist_01_{s}", "thigh_{s}", "calf_{s}", 0.5),
                ("calf_twist_01_{s}", "calf_{s}", "foot_{s}", 0.5),
            ),
            a_pose=True,
            description="Unreal Engine 4 mannequin; A-pose",
        ),
        Preset(
            "ue5",
            _UE_ROLES,
            spine=("spine_01", "spine_02", "spine_03", "spine_04", "spine_05"),
            necks=("neck_01", "neck_02"),
            root="root",
            finger="{finger}_{i}_{s}",
            finger_steps=("01", "02", "03"),
            extras=(
                ("upperarm_twist_01_{s}", "upperarm_{s}", "lowerarm_{s}", 0.33),
                ("upperarm_twist_02_{s}", "upperarm_{s}", "lowerarm_{s}", 0.66),
                ("lowerarm_twist_01_{s}", "lowerarm_{s}", "hand_{s}", 0.33),
                ("lowerarm_twist_02_{s}", "lowerarm_{s}", "hand_{s}", 0.66),
                ("thigh_twist_01_{s}", "thigh_{s}", "calf_{s}", 0.5),
                ("calf_twist_01_{s}", "calf_{s}", "foot_{s}", 0.5),
            ),
            a_pose=True,
            description="Unreal Engine 5 mannequin (Manny/Quinn); A-pose",
        ),
        Preset(
            "unity",
            _roles(
                "Hips",
                "Head",
                "{Side}Shoulder {Side}UpperArm {Side}LowerArm {Side}Hand {Side}UpperLeg {Side}LowerLeg {Side}Foot {Side}Toes",
            ),
            spine=("Spine", "Chest", "UpperChest"),
            necks=("Neck",),
            finger="{Side}{Finger}{i}",
            finger_steps=("Proximal", "Intermediate", "Distal"),
            finger_names={"thumb": "thumb", "index": "index", "middle": "middle", "ring": "ring", "pinky": "little"},
            description="Unity HumanBodyBones; T-pose",
        ),
        Preset(
            "vrm",
            _roles(
                "hips",
                "head",
                "{side}Shoulder {side}UpperArm {side}LowerArm {side}Hand {side}UpperLeg {side}LowerLeg {side}Foot {side}Toes",
            ),
            spine=("spine", "chest", "upperChest"),
            necks=("neck",),
            description="VRM humanoid bone names (lowerCamelCase); T-pose",
        ),
        Preset(
            "smpl",
            _SMPL_ROLES,
            spine=("spine1", "spine2", "spine3"),
            necks=("neck",),
            extras=(("{side}_hand", "{side}_wrist", "", 0.8),),
            description="SMPL body joints; T-pose",
        ),
        Preset(
            "smplx",
            _SMPL_ROLES,
            spine=("spine1", "spine2", "spine3"),
            necks=("neck",),
            finger="{side}_{finger}{i}",
            extras=(("jaw", "head", "", 0.4), ("{side}_eye_smplx", "head", "", 0.6)),
            description="SMPL-X body and hand joints; T-pose",
        ),
        Preset(
            "bvh",
            _MIXAMO_ROLES,
            spine=("Spine", "Spine1", "Spine2"),
            necks=("Neck",),
            description="common BVH exports (MotionBuilder-style names: Hips, Spine, LeftArm, LeftUpLeg, ...); T-pose",
        ),
    )
}


@cache
def preset_skeleton(name: str) -> Skeleton:
    return PRESETS[name].skeleton()
