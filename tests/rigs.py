"""Made rigs: a Bandai Namco (BN) motion rewritten onto another rig that moves exactly the same way.

Each made rig renames the BN joints with one rig family's public names (typed here by hand, not
taken from `models.motion.humanoid_presets`), inserts joints the BN skeleton lacks (extra spine
and neck joints, twist bones inside a limb, fingers), moves the rest pose (T-pose, A-pose, the
first frame, or BN's own zero pose), and may change units (m) and the up axis (Z). The world
positions of every original joint stay what they were in the BN motion (up to the unit and axis
change), which is the ground truth the humanoid mapping is checked against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.motion.bn_skeleton import PRIMARY_CHILD
from models.motion.retarget import default_rig
from models.motion.rotations import matrix_to_quat, quat_to_matrix
from models.motion.skeleton import Motion, Skeleton

Y_TO_Z = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # Y-up world -> Z-up world (right-handed)


@dataclass(frozen=True)
class RigSpec:
    name: str
    rename: dict[str, str | None]  # BN joint -> new name (None: drop joint_Root, the hips become the root)
    inserts: tuple[tuple[str, str, str, float], ...] = ()  # (new joint, BN parent, BN child or '' for a leaf, fraction)
    fingers: tuple[tuple[str, str], ...] = ()  # (finger joint, parent: a hand's new name or a finger's)
    rest: str = "zero"  # 'tpose', 'apose', 'first' or 'zero' (BN's own)
    up: str = "y"
    metres: bool = False

    @property
    def up_matrix(self) -> np.ndarray:
        return Y_TO_Z if self.up == "z" else np.eye(3)

    @property
    def unit(self) -> float:
        return 0.01 if self.metres else 1.0


def _sided(table: dict[str, str | None]) -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for bn, name in table.items():
        if name is not None and "{" in name:
            out[bn.replace("_X", "_L")] = name.format(Side="Left", side="left", S="L", s="l")
            out[bn.replace("_X", "_R")] = name.format(Side="Right", side="right", S="R", s="r")
        else:
            out[bn] = name
    return out


_BN_ARMS_LEGS = ("Shoulder_X", "UpperArm_X", "LowerArm_X", "Hand_X", "UpperLeg_X", "LowerLeg_X", "Foot_X", "Toes_X")


def _limbs(*names: str) -> dict[str, str | None]:
    return dict(zip(_BN_ARMS_LEGS, names))


SPECS = {
    s.name: s
    for s in (
        RigSpec(
            "mixamo",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "mixamorig:Hips",
                    "Spine": "mixamorig:Spine",
                    "Chest": "mixamorig:Spine2",
                    "Neck": "mixamorig:Neck",
                    "Head": "mixamorig:Head",
                    **_limbs(
                        "mixamorig:{Side}Shoulder",
                        "mixamorig:{Side}Arm",
                        "mixamorig:{Side}ForeArm",
                        "mixamorig:{Side}Hand",
                        "mixamorig:{Side}UpLeg",
                        "mixamorig:{Side}Leg",
                        "mixamorig:{Side}Foot",
                        "mixamorig:{Side}ToeBase",
                    ),
                }
            ),
            inserts=(("mixamorig:Spine1", "Spine", "Chest", 0.5),),
            fingers=(
                ("mixamorig:LeftHandIndex1", "mixamorig:LeftHand"),
                ("mixamorig:LeftHandIndex2", "mixamorig:LeftHandIndex1"),
                ("mixamorig:RightHandIndex1", "mixamorig:RightHand"),
            ),
            rest="tpose",
        ),
        RigSpec(
            "ue5",
            _sided(
                {
                    "joint_Root": "root",
                    "Hips": "pelvis",
                    "Spine": "spine_01",
                    "Chest": "spine_05",
                    "Neck": "neck_01",
                    "Head": "head",
                    **_limbs(
                        "clavicle_{s}",
                        "upperarm_{s}",
                        "lowerarm_{s}",
                        "hand_{s}",
                        "thigh_{s}",
                        "calf_{s}",
                        "foot_{s}",
                        "ball_{s}",
                    ),
                }
            ),
            inserts=(
                ("spine_02", "Spine", "Chest", 0.25),
                ("spine_03", "spine_02", "Chest", 0.33),
                ("spine_04", "spine_03", "Chest", 0.5),
                ("neck_02", "Neck", "Head", 0.5),
                ("upperarm_twist_01_l", "UpperArm_L", "", 0.5),
                ("upperarm_twist_01_r", "UpperArm_R", "", 0.5),
                ("lowerarm_twist_01_l", "LowerArm_L", "Hand_L", 0.6),
                ("thigh_twist_01_r", "UpperLeg_R", "LowerLeg_R", 0.4),
            ),
            fingers=(("index_01_l", "hand_l"), ("index_02_l", "index_01_l"), ("thumb_01_r", "hand_r")),
            rest="apose",
            up="z",
        ),
        RigSpec(
            "smplx",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "pelvis",
                    "Spine": "spine1",
                    "Chest": "spine3",
                    "Neck": "neck",
                    "Head": "head",
                    **_limbs(
                        "{side}_collar",
                        "{side}_shoulder",
                        "{side}_elbow",
                        "{side}_wrist",
                        "{side}_hip",
                        "{side}_knee",
                        "{side}_ankle",
                        "{side}_foot",
                    ),
                }
            ),
            inserts=(("spine2", "Spine", "Chest", 0.5), ("jaw", "Head", "", 0.3)),
            fingers=(("left_index1", "left_wrist"), ("left_index2", "left_index1"), ("right_thumb1", "right_wrist")),
            rest="first",
            metres=True,
        ),
        RigSpec(
            "unity",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "Hips",
                    "Spine": "Spine",
                    "Chest": "Chest",
                    "Neck": "Neck",
                    "Head": "Head",
                    **_limbs(
                        "{Side}Shoulder",
                        "{Side}UpperArm",
                        "{Side}LowerArm",
                        "{Side}Hand",
                        "{Side}UpperLeg",
                        "{Side}LowerLeg",
                        "{Side}Foot",
                        "{Side}Toes",
                    ),
                }
            ),
            rest="tpose",
            up="z",
            metres=True,
        ),
        RigSpec(
            "bvh",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "Hips",
                    "Spine": "Spine",
                    "Chest": "Spine1",
                    "Neck": "Neck",
                    "Head": "Head",
                    **_limbs(
                        "{Side}Shoulder",
                        "{Side}Arm",
                        "{Side}ForeArm",
                        "{Side}Hand",
                        "{Side}UpLeg",
                        "{Side}Leg",
                        "{Side}Foot",
                        "{Side}ToeBase",
                    ),
                }
            ),
            inserts=(
                ("LeftForeArmRoll", "LowerArm_L", "Hand_L", 0.5),
                ("RightForeArmRoll", "LowerArm_R", "Hand_R", 0.5),
            ),
            rest="zero",
            metres=True,
        ),
        RigSpec(
            "ue4",
            _sided(
                {
                    "joint_Root": "root",
                    "Hips": "pelvis",
                    "Spine": "spine_01",
                    "Chest": "spine_03",
                    "Neck": "neck_01",
                    "Head": "head",
                    **_limbs(
                        "clavicle_{s}",
                        "upperarm_{s}",
                        "lowerarm_{s}",
                        "hand_{s}",
                        "thigh_{s}",
                        "calf_{s}",
                        "foot_{s}",
                        "ball_{s}",
                    ),
                }
            ),
            inserts=(("spine_02", "Spine", "Chest", 0.5), ("calf_twist_01_l", "LowerLeg_L", "", 0.5)),
            rest="apose",
        ),
        RigSpec(
            "vrm",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "hips",
                    "Spine": "spine",
                    "Chest": "upperChest",
                    "Neck": "neck",
                    "Head": "head",
                    **_limbs(
                        "{side}Shoulder",
                        "{side}UpperArm",
                        "{side}LowerArm",
                        "{side}Hand",
                        "{side}UpperLeg",
                        "{side}LowerLeg",
                        "{side}Foot",
                        "{side}Toes",
                    ),
                }
            ),
            inserts=(("chest", "Spine", "Chest", 0.5),),
            fingers=(("leftThumbProximal", "leftHand"),),
            rest="tpose",
        ),
        RigSpec(
            "smpl",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "pelvis",
                    "Spine": "spine1",
                    "Chest": "spine3",
                    "Neck": "neck",
                    "Head": "head",
                    **_limbs(
                        "{side}_collar",
                        "{side}_shoulder",
                        "{side}_elbow",
                        "{side}_wrist",
                        "{side}_hip",
                        "{side}_knee",
                        "{side}_ankle",
                        "{side}_foot",
                    ),
                }
            ),
            inserts=(
                ("spine2", "Spine", "Chest", 0.5),
                ("left_hand", "Hand_L", "", 0.5),
                ("right_hand", "Hand_R", "", 0.5),
            ),
            rest="tpose",
            metres=True,
        ),
        RigSpec(
            "blender",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "hips",
                    "Spine": "spine",
                    "Chest": "chest",
                    "Neck": "neck",
                    "Head": "head",
                    **_limbs(
                        "shoulder.{S}",
                        "upper_arm.{S}",
                        "forearm.{S}",
                        "hand.{S}",
                        "thigh.{S}",
                        "shin.{S}",
                        "foot.{S}",
                        "toe.{S}",
                    ),
                }
            ),
            rest="first",
            up="z",
            metres=True,
        ),
    )
}

# Rigs outside the presets' naming, for the tests that need a rig the matching has never seen
# (an Xsens MVN-style capture export: four spine joints L5/L3/T12/T8, Z up, metres, A-pose) or a
# VMC sender's avatar (Unity HumanBodyBones with Chest and UpperChest, eyes and fingers, Y up,
# metres, the normalised T-pose VMC senders send).
EXTRA_SPECS = {
    s.name: s
    for s in (
        RigSpec(
            "xsens",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "Pelvis",
                    "Spine": "L5",
                    "Chest": "T8",
                    "Neck": "Neck",
                    "Head": "Head",
                    **_limbs(
                        "{Side}Shoulder",
                        "{Side}UpperArm",
                        "{Side}ForeArm",
                        "{Side}Hand",
                        "{Side}UpperLeg",
                        "{Side}LowerLeg",
                        "{Side}Foot",
                        "{Side}Toe",
                    ),
                }
            ),
            inserts=(("L3", "Spine", "Chest", 0.33), ("T12", "L3", "Chest", 0.5)),
            fingers=(("LeftFingerIndex1", "LeftHand"), ("RightFingerIndex1", "RightHand")),
            rest="apose",
            up="z",
            metres=True,
        ),
        RigSpec(
            "vmc",
            _sided(
                {
                    "joint_Root": None,
                    "Hips": "Hips",
                    "Spine": "Spine",
                    "Chest": "UpperChest",
                    "Neck": "Neck",
                    "Head": "Head",
                    "ChestLow": "Chest",
                    **_limbs(
                        "{Side}Shoulder",
                        "{Side}UpperArm",
                        "{Side}LowerArm",
                        "{Side}Hand",
                        "{Side}UpperLeg",
                        "{Side}LowerLeg",
                        "{Side}Foot",
                        "{Side}Toes",
                    ),
                }
            ),
            inserts=(("ChestLow", "Spine", "Chest", 0.5), ("LeftEye", "Head", "", 0.5), ("RightEye", "Head", "", 0.5)),
            fingers=(
                ("LeftIndexProximal", "LeftHand"),
                ("LeftIndexIntermediate", "LeftIndexProximal"),
                ("RightThumbProximal", "RightHand"),
            ),
            rest="tpose",
            metres=True,
        ),
    )
}


def mirrored(motion: Motion, reflection: np.ndarray) -> Motion:
    """The same motion written in a mirrored world frame (`reflection`, an orthogonal matrix of
    determinant -1): offsets and translations reflected, every rotation conjugated (M R M^T,
    still a proper rotation). A left-handed client sends this for the motion a right-handed one
    sends as `motion`; joint names (Left/Right) stay, the body is the same."""
    m = np.asarray(reflection, dtype=float)
    local = m @ quat_to_matrix(motion.rotations) @ m.T
    sk = motion.skeleton
    skeleton = Skeleton(sk.names, sk.parents, sk.offsets @ m.T, sk.end_sites @ m.T)
    return Motion(skeleton, matrix_to_quat(local), motion.translations @ m.T, motion.fps, motion.euler_orders)


# T-pose bone directions (Y up, facing +Z, left = +X) of each BN joint's main bone
# a T-pose stands on flat feet: BN's ankle-toe bone falls by its flat-foot pitch (`retarget.flat_foot_pitch`)
_FOOT = (0.0, -float(np.sin(default_rig().foot_pitch or 0.0)), float(np.cos(default_rig().foot_pitch or 0.0)))
_TPOSE = {
    "Hips": (0, 1, 0),
    "Spine": (0, 1, 0),
    "Chest": (0, 1, 0),
    "Neck": (0, 1, 0),
    "Shoulder_L": (1, 0, 0),
    "UpperArm_L": (1, 0, 0),
    "LowerArm_L": (1, 0, 0),
    "Shoulder_R": (-1, 0, 0),
    "UpperArm_R": (-1, 0, 0),
    "LowerArm_R": (-1, 0, 0),
    "UpperLeg_L": (0, -1, 0),
    "LowerLeg_L": (0, -1, 0),
    "Foot_L": _FOOT,
    "UpperLeg_R": (0, -1, 0),
    "LowerLeg_R": (0, -1, 0),
    "Foot_R": _FOOT,
}


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction a to direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def make_rig(bn: Motion, spec: RigSpec) -> Motion:
    """The BN motion `bn` on the made rig `spec` (same world motion, new names/joints/rest/units/axes)."""
    sk = bn.skeleton
    names, parents = list(sk.names), list(int(p) for p in sk.parents)
    local = list(np.moveaxis(quat_to_matrix(bn.rotations), 1, 0))  # per joint (F, 3, 3)
    trans = list(np.moveaxis(bn.translations.copy(), 1, 0))  # per joint (F, 3)
    f = bn.num_frames
    rng = np.random.default_rng(len(spec.name))

    def add(name: str, parent: int, t: np.ndarray, rot: np.ndarray | None = None) -> int:
        names.append(name)
        parents.append(parent)
        trans.append(np.broadcast_to(t, (f, 3)).copy())
        local.append(np.broadcast_to(np.eye(3) if rot is None else rot, (f, 3, 3)).copy())
        return len(names) - 1

    for new, parent, child, frac in spec.inserts:
        p = names.index(parent)
        if child:  # inside the bone parent -> child: the child hangs from the new joint, same place
            c = names.index(child)
            n = add(new, p, frac * trans[c][0])
            trans[c] = (1 - frac) * trans[c]
            parents[c] = n
        else:  # a leaf halfway along the parent's main bone
            c = names.index(PRIMARY_CHILD.get(parent, parent))
            add(new, p, frac * trans[c][0] if c != p else np.array([0.0, 5.0, 0.0]))
    for new, parent in spec.fingers:
        p = (
            names.index(parent)
            if parent in names
            else names.index(next(b for b, n in spec.rename.items() if n == parent))
        )
        up = trans[p][0] if np.linalg.norm(trans[p][0]) > 1e-9 else np.array([3.0, 0, 0])
        tilt = matrix_from_rotvec(rng.normal(size=3) * 0.3)
        add(new, p, 0.15 * up, tilt)  # fingers: a constant curl, which must pass through

    order = _parents_first(parents)
    names = [names[j] for j in order]
    remap = {j: i for i, j in enumerate(order)}
    parents = [remap[parents[j]] if parents[j] >= 0 else -1 for j in order]
    local = np.stack([local[j] for j in order], axis=1)
    trans = np.stack([trans[j] for j in order], axis=1)

    if spec.rename.get("joint_Root", "x") is None:  # drop the static root: the hips carry world translation
        r = names.index("joint_Root")
        assert r == 0 and np.allclose(local[:, 0], np.eye(3)) and np.allclose(trans[:, 0], 0)
        names, local, trans = names[1:], local[:, 1:], trans[:, 1:]
        parents = [p - 1 if p > 0 else -1 for p in parents[1:]]

    # rest pose: C_j (world rotation of joint j's frame at rest, inverted); L' = C_p^T L C_j, t' = C_p^T t
    g = _world(local, parents)
    c = np.broadcast_to(np.eye(3), (len(names), 3, 3)).copy()
    if spec.rest == "first":
        c = np.swapaxes(g[0], -1, -2)
    elif spec.rest in ("tpose", "apose"):
        rest_pos = np.zeros((len(names), 3))
        for j, p in enumerate(parents):
            rest_pos[j] = trans[0, j] + (rest_pos[p] if p >= 0 else 0)
        for j, name in enumerate(names):
            bn_name = name
            if bn_name in _TPOSE:
                target = np.array(_TPOSE[bn_name], float)
                if spec.rest == "apose" and ("Arm" in bn_name):
                    target = target + np.array([0, -1.0, 0])
                child = names.index(PRIMARY_CHILD[bn_name])
                while parents[child] != j:
                    child = parents[child]
                c[j] = _swing(trans[0, child], target).T
            elif parents[j] >= 0:
                c[j] = c[parents[j]]
    cp = np.stack([c[p] if p >= 0 else np.eye(3) for p in parents])
    local = np.swapaxes(cp, -1, -2)[None] @ local @ c[None]
    trans = (np.swapaxes(cp, -1, -2)[None] @ trans[..., None])[..., 0]

    m = spec.up_matrix  # axes: conjugate every rotation, rotate every translation
    local = m @ local @ m.T
    trans = (trans @ m.T) * spec.unit
    final = [spec.rename.get(n, n) for n in names]
    skeleton = Skeleton(tuple(final), np.array(parents), trans[0].copy(), np.full((len(final), 3), np.nan))
    return Motion(skeleton, matrix_to_quat(local), trans, bn.fps)


def matrix_from_rotvec(v: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(v).as_matrix()


def _parents_first(parents: list[int]) -> list[int]:
    """Depth-first order (children in index order), the order a BVH file lists joints in."""
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(p, []).append(j)
    order: list[int] = []
    stack = list(reversed(children.get(-1, [])))
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children.get(j, [])))
    return order


def _world(local: np.ndarray, parents: list[int]) -> np.ndarray:
    g = local.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            g[:, j] = g[:, p] @ local[:, j]
    return g


def bn_positions(motion: Motion, spec: RigSpec) -> np.ndarray:
    """World positions of a made-rig motion back in BN's world (cm, Y up)."""
    return (motion.global_positions() / spec.unit) @ spec.up_matrix


# --------------------------------------------------------------------------- made rigs on the wire


def as_bvh_file(motion: Motion) -> tuple[str, Motion]:
    """(BVH header, the motion read back from the whole file): what a client sends (a BVH lists
    joints depth first, Euler angles at 9 decimals)."""
    from models.motion import bvh
    from models.motion.skeleton import from_bvh, to_bvh

    motion.euler_orders = tuple("ZXY" for _ in motion.skeleton.names)
    text = bvh.dumps(to_bvh(motion), precision=9)
    return text.split("MOTION")[0], from_bvh(bvh.parse(text))


def stream(
    base: str, start: dict, root: np.ndarray, rot: np.ndarray, model: str = "lti", style: str = "elderly"
) -> tuple[dict, np.ndarray, np.ndarray]:
    """(started, roots (F, 3), rotations (F, J, 4)) of frames streamed one at a time through a
    session of the server at `base` (JSON frames: float32 on the wire is the binary encoding's)."""
    import json

    from websockets.sync.client import connect

    with connect(base.replace("http", "ws") + "/v1/stream") as ws:
        ws.send(json.dumps({"type": "start", "model": model, "style": style, **start}))
        started = json.loads(ws.recv(timeout=20))
        assert started["type"] == "started", started
        roots, rots = [], []
        for t in range(len(root)):
            ws.send(json.dumps({"type": "frame", "seq": t, "root": root[t].tolist(), "rotations": rot[t].tolist()}))
            reply = json.loads(ws.recv(timeout=20))
            assert reply["type"] == "frame", reply
            roots.append(reply["root"])
            rots.append(reply["rotations"])
    return started, np.array(roots), np.array(rots)


def stream_made_rig(
    base: str, motion: Motion, spec: RigSpec, model: str, style: str = "elderly", **start
) -> tuple[dict, Motion]:
    """A made-rig motion through a session as a BVH client sends it (its header; the hips'
    translation per frame); (started, the stylised motion on the same rig)."""
    header, m = as_bvh_file(motion)
    hips = m.skeleton.index(spec.rename["Hips"])
    started, root, rot = stream(
        base, {"bvh_header": header, **start}, m.translations[:, hips], m.rotations, model, style
    )
    trans = m.translations.copy()
    trans[:, hips] = root
    return started, Motion(m.skeleton, rot, trans, m.fps)


def mapped_error(styled: Motion, spec: RigSpec, bn_output: np.ndarray, bn: Skeleton) -> np.ndarray:
    """(F, roles) distance (cm) between the made rig's mapped joints and the same joints of the
    model-rig output `bn_output` (F, 22, 3), both relative to their hips: the round-trip error."""
    from models.motion.humanoid import BN_ROLES

    got = bn_positions(styled, spec)
    sk = styled.skeleton
    hips_c, hips_b = sk.index(spec.rename["Hips"]), bn.index("Hips")
    pairs = [(sk.index(spec.rename[b]), bn.index(b)) for b in BN_ROLES if b != "Hips"]
    return np.linalg.norm(
        (got[:, [a for a, _ in pairs]] - got[:, [hips_c]])
        - (bn_output[:, [b for _, b in pairs]] - bn_output[:, [hips_b]]),
        axis=-1,
    )
