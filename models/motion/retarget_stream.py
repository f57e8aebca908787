"""Causal, per-frame retargeting between a client's humanoid rig and the Bandai Namco (BN) skeleton.

`FrameRetargeter` fixes the mapping up front (`retarget`). The client's world is brought to BN's
(Y up, right-handed) by `HumanoidRig.axes`; the Hips translation is the client's scaled by the
leg-length ratio, plus a height (`vertical_offset`) that puts its toes at BN's floor.

`to_source` maps a (stylised) BN frame back: client joint k gets G_new[k] = D_j G_client[k], D_j
the change of the global rotation of its nearest mapped ancestor-or-self; unmapped joints keep
their local rotations, so `to_source(*to_model(root, rot), rot) == (root, rot)` up to rounding.
Both run compiled kernels; `tests/reference/retarget.py` is the numpy mapping they equal.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from . import retarget_kernels as kernels
from .bn_skeleton import BN_JOINTS, PRIMARY_CHILD
from .humanoid import BN_ROLES, HumanoidRig, bn_joints_of, bn_segments, humanoid_rig, leg_length
from .retarget import _HINGES, _LATERAL, Rig, TwistPlan, _frame, default_rig
from .rotations import matrix_to_quat as mat_to_quat
from .skeleton import Skeleton, depths, fk


class _Tree:
    """FK over a joint subset, one `matmul` per tree depth (joints stored depth by depth)."""

    def __init__(self, parents: np.ndarray, needed: np.ndarray | None = None):
        parents = np.asarray(parents)
        n = len(parents)
        depth = depths(parents)
        keep = np.ones(n, bool)
        if needed is not None:  # the needed joints and their ancestors
            keep[:] = False
            for j in needed:
                while j >= 0 and not keep[j]:
                    keep[j], j = True, int(parents[j])
        self.order = np.array(sorted(np.flatnonzero(keep), key=lambda j: (depth[j], j)))
        self.pos = np.full(n, -1)  # joint -> slot in `order`
        self.pos[self.order] = np.arange(len(self.order))
        d = depth[self.order]
        self.levels = [
            (int(np.searchsorted(d, k)), int(np.searchsorted(d, k, "right")), self.pos[parents[self.order[d == k]]])
            for k in range(1, int(d.max(initial=0)) + 1)
        ]


def _path_terms(skeleton: Skeleton, a: int, b: int) -> list[tuple[int, float]]:
    """(joint k, sign): pos[b] - pos[a] = sum sign * G[parent k] @ offset[k], zero offsets dropped."""

    def up(j: int) -> list[int]:
        chain = []
        while j >= 0:
            chain.append(j)
            j = int(skeleton.parents[j])
        return chain

    ca, cb = up(a), up(b)
    common = next(j for j in ca if j in cb)
    terms = [(k, 1.0) for k in cb[: cb.index(common)]] + [(k, -1.0) for k in ca[: ca.index(common)]]
    return [(k, s) for k, s in terms if np.linalg.norm(skeleton.offsets[k]) > 1e-9]


def _chain(skeleton: Skeleton, a: int, b: int) -> list[int]:
    """The joints below ancestor a down to b (b included), top first: the bones of the path."""
    out = []
    while b != a:
        out.append(b)
        b = int(skeleton.parents[b])
    return out[::-1]


def _along(skeleton: Skeleton, chain: list[int], share: float) -> np.ndarray:
    """(len(chain),) weights placing a point `share` of the chain's length from its top."""
    lengths = np.array([np.linalg.norm(skeleton.offsets[k]) for k in chain])
    start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    reach = share * lengths.sum()
    return np.clip((reach - start) / np.where(lengths > 0, lengths, 1.0), 0.0, 1.0) * (lengths > 1e-9)


def trunk_bones(src: Skeleton, roles: dict[str, int], bn: Skeleton) -> dict[str, list[tuple[int, float]]]:
    """BN trunk joint -> the client vector its bone takes, each at its share of the hips-head chain."""
    chain = _chain(src, roles["hips"], roles["head"])
    names = ["Hips"]
    while names[-1] != "Head":
        names.append(PRIMARY_CHILD[names[-1]])
    lengths = np.array([np.linalg.norm(bn.offsets[bn.index(n)]) for n in names[1:]])
    share = np.concatenate([[0.0], np.cumsum(lengths)]) / lengths.sum()
    points = [_along(src, chain, f) for f in share]
    return {n: list(zip(chain, points[i + 1] - points[i])) for i, n in enumerate(names[:-1])}


# Two-vector joints whose side vector is the rest-pose line carried by the joint's own rotation
# (`_rest_side`), not read per frame. Not the Chest: forward collars would turn it.
_REST_SIDE = ("Hips",)


def _rest_side(skeleton: Skeleton, a: int, b: int) -> np.ndarray:
    """pos[b] - pos[a] at rest, carried by the hips' rotation (joints between hips and thighs ignored)."""
    return sum((s * skeleton.offsets[k] for k, s in _path_terms(skeleton, a, b)), np.zeros(3))


# A rest pose stands (its feet flat, `_sole_terms`) when each leg hangs within STANDING_LEG of
# straight down and the soles mirror each other within STANDING_FEET.
STANDING_LEG, STANDING_FEET = np.radians(30.0), np.radians(3.0)


def _sole_terms(hr: HumanoidRig, rig: Rig) -> dict[str, list[tuple[object, int, np.ndarray, float]]]:
    """BN foot -> the client's ankle-toe vector pitched to BN's flat foot, where its rest pose stands."""
    src, roles = hr.skeleton, hr.roles
    up = hr.axes.T @ np.array([0.0, 1.0, 0.0])  # the client's up
    if rig.foot_pitch is None or not all(f"toes_{s}" in roles for s in "lr"):
        return {}
    legs = [_rest_side(src, roles[f"upperleg_{s}"], roles[f"foot_{s}"]) for s in "lr"]
    soles = [_rest_side(src, roles[f"foot_{s}"], roles[f"toes_{s}"]) for s in "lr"]
    sides = [np.cross(sole, -up) for sole in soles]
    pitch = [np.arcsin(np.clip(-sole @ up / np.linalg.norm(sole), -1.0, 1.0)) for sole in soles]
    if (
        any(-leg @ up < np.cos(STANDING_LEG) * np.linalg.norm(leg) for leg in legs)
        or any(np.linalg.norm(side) < 1e-3 * np.linalg.norm(sole) for side, sole in zip(sides, soles))
        or abs(pitch[0] - pitch[1]) > STANDING_FEET
    ):
        return {}
    return {
        f"Foot_{s.upper()}": [
            (
                ("sole", s),
                roles[f"foot_{s}"],
                Rotation.from_rotvec(side / np.linalg.norm(side) * (rig.foot_pitch - p)).apply(sole),
                1.0,
            )
        ]
        for s, side, sole, p in zip("lr", sides, soles, pitch)
    }


# --------------------------------------------------------------------------- the retargeter


# A stream's hinge state per BN limb joint (`retarget._HINGES`): the weighted axis sum (3), weights (1).
HINGE_STATE = (len(_HINGES), 4)


class FrameRetargeter:
    """Per-frame client rig <-> BN retargeting for one client rig.

    Fixed after construction but for each stream's hinge state (`init_state`: the client's hinge axis
    per limb as its bent frames show it), one row per stream kept by the caller. `source`: a matched
    `HumanoidRig` or a skeleton; `source_floor`: where its toes touch the ground (client units);
    `vertical_offset` overrides the derived Hips height shift.
    """

    def __init__(
        self,
        source: Skeleton | HumanoidRig,
        rig: Rig | None = None,
        source_floor: float | None = None,
        vertical_offset: float | None = None,
    ):
        rig = default_rig() if rig is None else rig
        hr = source if isinstance(source, HumanoidRig) else humanoid_rig(source)
        src, sk, roles = hr.skeleton, rig.skeleton, hr.roles
        self.humanoid, self.source, self.rig = hr, src, rig
        if sk.parents[sk.index("Hips")] < 0:
            raise ValueError("expected Hips to have a parent (joint_Root) in BN")
        self._axes = hr.axes  # client world -> BN world
        self._bn_tree = _Tree(sk.parents)
        self._src_parents = np.asarray(src.parents)
        self._bn_parents = np.asarray(sk.parents)
        self._bn_hips = sk.index("Hips")
        self._hips = roles["hips"]

        # Vectors read per frame: BN bone segments, then (up, side) per two-vector joint.
        segs = bn_segments(roles)
        plain = tuple(n for n in BN_JOINTS if n in segs and n not in _LATERAL)
        trunk = trunk_bones(src, roles, sk)  # the trunk by length
        bone: dict[str, list[tuple[object, int, np.ndarray, float]]] = {
            n: [(k, int(src.parents[k]), src.offsets[k], w) for k, w in t if w != 0.0] for n, t in trunk.items()
        }
        bone.update(_sole_terms(hr, rig))
        terms = [
            bone[n] if n in bone else self._segment_terms(src, roles[segs[n][0]], roles[segs[n][1]]) for n in plain
        ]
        m_tgt = []
        for name, (tl, tr) in _LATERAL.items():
            side = (BN_ROLES[tr].replace("clavicle", "upperarm"), BN_ROLES[tl].replace("clavicle", "upperarm"))
            anchor = roles[segs[name][0]]
            terms += [bone[name]]
            if name in _REST_SIDE:
                terms += [[(("side", name), anchor, _rest_side(src, roles[side[0]], roles[side[1]]), 1.0)]]
            else:
                terms += [self._segment_terms(src, roles[side[0]], roles[side[1]])]
            off = lambda n: sk.offsets[sk.index(n)]  # noqa: E731
            m_tgt.append(_frame(off(PRIMARY_CHILD[name]), off(tl) - off(tr)))
        # Then the feet: hips -> each foot point (toes and ankles), for `_drop`.
        points = [(f"{p}_{x}", f"{b}_{x.upper()}") for p, b in (("toes", "Toes"), ("foot", "Foot")) for x in "lr"]
        points = [(r, b) for r, b in points if r in roles]
        terms += [self._segment_terms(src, roles["hips"], roles[r]) for r, _ in points]
        chains = []  # per BN foot point, (parent joint, offset) of each joint from the Hips down to it
        for _, b in points:
            chain, j = [], sk.index(b)
            while sk.names[j] != "Hips":
                chain.append((int(sk.parents[j]), sk.offsets[j]))
                j = int(sk.parents[j])
            chains.append(chain[::-1] + [(-1, np.zeros(3))] * (4 - len(chain)))
        self._drop_par = np.array([[p for p, _ in c] for c in chains], dtype=int)  # (P, 4), -1: padding
        self._drop_off = np.array([[o for _, o in c] for c in chains])  # (P, 4, 3)
        self._drop_kind = [r.split("_")[0] for r, _ in points]
        # each point's height below the hips when standing (`_standing_offset`): client, BN
        self._drop_ref = np.zeros((2, len(points)))
        keys = sorted({key for t in terms for key, *_ in t}, key=str)
        flat = {key: (par, vec) for t in terms for key, par, vec, _ in t}
        self._num_plain = len(plain)
        self._vec_off = np.array([flat[key][1] for key in keys])[:, :, None]  # (T, 3, 1)
        vec_par = np.array([flat[key][0] for key in keys], dtype=int)
        self._vec_coef = np.zeros((len(terms), len(keys)))
        for v, t in enumerate(terms):
            for key, _, _, sign in t:
                self._vec_coef[v, keys.index(key)] += sign
        self._m_tgt_t = np.swapaxes(np.stack(m_tgt), -1, -2)  # (L, 3, 3), transposed
        self._plan = TwistPlan(rig, plain)

        # Hips position = c + Gp @ t, t the translated joint's translation (the frame's root)
        above = [self._hips]
        while self._src_parents[above[-1]] >= 0:
            above.append(int(self._src_parents[above[-1]]))
        self._translated = hr.translated
        self._chain_fixed = [k for k in above if k != hr.translated]  # joints contributing their offset

        # to_source: each client joint takes the delta of the BN joint of its nearest mapped ancestor
        mapped = {roles[r]: sk.index(b) for r, b in bn_joints_of(roles).items()}
        none = sk.num_joints  # an identity delta for joints with no mapped ancestor (above the hips)
        anc = np.full(src.num_joints, none)
        for k in range(src.num_joints):
            j = k
            while j >= 0 and j not in mapped:
                j = int(src.parents[j])
            if j >= 0:
                anc[k] = mapped[j]
        self._mapped = np.array(sorted(mapped), dtype=int)
        self._mapped_nonroot = np.array([k for k in self._mapped if src.parents[k] >= 0], dtype=int)
        self._mapped_root = np.array([k for k in self._mapped if src.parents[k] < 0], dtype=int)
        chain_par = [int(self._src_parents[k]) for k in above if self._src_parents[k] >= 0]
        # per BN limb joint, the client joint whose frame holds its hinge axis: the hinge child's parent
        hinge_of = {
            sk.index(n): int(src.parents[roles[BN_ROLES[c]]]) for n, c in _HINGES.items() if BN_ROLES[c] in roles
        }
        needed = np.unique(
            np.concatenate(
                [
                    vec_par,
                    self._mapped,
                    self._src_parents[self._mapped_nonroot],
                    chain_par,
                    [self._hips],
                    list(hinge_of.values()),
                ]
            ).astype(int)
        )
        tree = self._src_tree = _Tree(src.parents, needed)  # client world rotations live in tree slots
        self._hinge_slot = {j: int(tree.pos[k]) for j, k in hinge_of.items()}
        self._vec_par_s = tree.pos[vec_par]
        self._anc_bn_s = anc[tree.order]
        self._mapped_s = tree.pos[self._mapped_nonroot]
        self._mapped_parents_s = tree.pos[self._src_parents[self._mapped_nonroot]]
        self._mapped_root_s = tree.pos[self._mapped_root]
        self._fixed_par_s = np.array(
            [tree.pos[self._src_parents[k]] if self._src_parents[k] >= 0 else -1 for k in self._chain_fixed], dtype=int
        )
        self._fixed_off = src.offsets[self._chain_fixed]
        p = int(self._src_parents[hr.translated])
        self._translated_par_s = int(tree.pos[p]) if p >= 0 else -1

        self._kernel_plan()
        self.scale = leg_length(sk) / hr.leg_length
        self.source_floor = rig.floor / self.scale if source_floor is None else float(source_floor)
        self.vertical_offset = self._standing_offset() if vertical_offset is None else float(vertical_offset)

    # ----------------------------------------------------------------------- internals

    @staticmethod
    def _segment_terms(src: Skeleton, a: int, b: int) -> list[tuple[object, int, np.ndarray, float]]:
        """pos[b] - pos[a] as terms (key, parent joint, offset, sign): sign * G[parent] @ offset."""
        return [(k, int(src.parents[k]), src.offsets[k], sign) for k, sign in _path_terms(src, a, b)]

    def _standing_offset(self) -> float:
        """Hips height shift: BN's toes at `rig.floor`, the client's at `source_floor`."""
        sk, src, roles = self.rig.skeleton, self.source, self.humanoid.roles
        rest = np.zeros((1, src.num_joints, 4))
        rest[..., 3] = 1.0
        self.vertical_offset = 0.0
        _, rot = self.to_source(np.zeros((1, 3)), self.rig.pose[None], rest)
        trans = np.broadcast_to(src.offsets, (1, src.num_joints, 3)).copy()
        c_pos = fk(rot, trans, src.parents)[1][0] @ self._axes.T
        _, local = self.to_model(trans[:, self._translated], rot)
        bn_trans = np.broadcast_to(sk.offsets, (1, sk.num_joints, 3)).copy()
        b_pos = fk(local, bn_trans, sk.parents)[1][0]
        # each foot point's standing height below the hips (per kind, the lower side's), for `_drop`
        pts = (
            [roles[f"{k}_{x}"] for k in ("toes", "foot") for x in "lr" if f"{k}_{x}" in roles],
            [
                sk.index(f"{b}_{x}")
                for k, b in (("toes", "Toes"), ("foot", "Foot"))
                for x in "LR"
                if f"{k}_{x.lower()}" in roles
            ],
        )
        for row, (pos, hips) in enumerate(((c_pos, self._hips), (b_pos, self._bn_hips))):
            rel = pos[pts[row], 1] - pos[hips, 1]
            self._drop_ref[row] = [
                rel[[i for i, x in enumerate(self._drop_kind) if x == k]].min() for k in self._drop_kind
            ]
        self._kernel_plan()
        hips_bn, _ = self.to_model(trans[:, self._translated], rot)
        bn_trans[:, self._bn_hips] = hips_bn
        b_pos = fk(local, bn_trans, sk.parents)[1][0]
        part = "toes" if all(f"toes_{s}" in roles for s in "lr") else "foot"
        ref_c = [roles[f"{part}_{s}"] for s in "lr"]
        ref_b = [sk.index(f"{'Toes' if part == 'toes' else 'Foot'}_{s}") for s in "LR"]
        toes_b = [sk.index(f"Toes_{s}") for s in "LR"]
        t_c = c_pos[ref_c, 1].mean() - c_pos[self._hips, 1]  # reference joints below the hips
        t_bn_toe = b_pos[toes_b, 1].mean() - b_pos[self._bn_hips, 1]
        t_bn_ref = b_pos[ref_b, 1].mean() - b_pos[self._bn_hips, 1]
        h = self.source_floor + (t_bn_ref - t_bn_toe) / self.scale - t_c  # client hips height, standing
        drop = hips_bn[0, 1] - self.scale * c_pos[self._hips, 1]  # `_drop` in this pose, which to_model added
        return float(self.rig.floor - t_bn_toe - self.scale * h - drop)

    # ----------------------------------------------------------------------- API

    @staticmethod
    def init_state(streams: int = 1) -> np.ndarray:
        """(streams, *HINGE_STATE) fresh hinge state; one shape for every rig, so rows stack."""
        return np.zeros((streams, *HINGE_STATE))

    def to_model(
        self, root: np.ndarray, rotations: np.ndarray, state: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Client frame(s) -> BN frame(s), compiled (microseconds a frame).

        root (B, 3), rotations (B, Js, 4) (xyzw); state: None (a fresh stream), (B, *HINGE_STATE) (row b:
        stream b) or (1, ...) (the rows: that stream's next frames), updated in place.
        Returns (Hips translation (B, 3), BN local rotations (B, 22, 4), w >= 0)."""
        root = np.ascontiguousarray(root, dtype=np.float64).reshape(-1, 3)
        b = root.shape[0]
        rotations = self._client_rotations(rotations, b)
        hinges = self._state(state, b)
        hips, out = np.empty((b, 3)), np.empty((b, self._bn_parents.shape[0], 4))
        kernels.to_model(root, rotations, *self._k_plan, self.scale, self.vertical_offset, hinges, True, hips, out)
        return hips, out

    def to_source(
        self,
        root_bn: np.ndarray,
        rotations_bn: np.ndarray,
        source_rotations: np.ndarray,
        state: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """BN frame(s) -> client frame(s), compiled.

        source_rotations (B, Js, 4): the client's own rotations for the same frames (unmapped joints keep
        them); state: None (learned again from them) or what `to_model` left (read only).
        Returns (client root translation (B, 3), client local rotations (B, Js, 4))."""
        root_bn = np.ascontiguousarray(root_bn, dtype=np.float64).reshape(-1, 3)
        b = root_bn.shape[0]
        nb = self._bn_parents.shape[0]
        rotations_bn = np.ascontiguousarray(rotations_bn, dtype=np.float64).reshape(b, nb, 4)
        source_rotations = self._client_rotations(source_rotations, b)
        hinges = self._state(state, b)
        root, out = np.empty((b, 3)), np.empty_like(source_rotations)
        frame = (root_bn, rotations_bn, source_rotations)
        kernels.to_source(*frame, *self._k_plan, self.scale, self.vertical_offset, hinges, state is None, root, out)
        return root, out

    # ----------------------------------------------------------------------- compiled kernels

    def _state(self, state: np.ndarray | None, b: int) -> np.ndarray:
        if state is None:
            return self.init_state()
        if state.shape not in ((b, *HINGE_STATE), (1, *HINGE_STATE)) or state.dtype != np.float64:
            raise ValueError(
                f"expected a float64 hinge state of shape ({b} or 1, 4, 4), got {state.dtype} {state.shape}"
            )
        if not state.flags.c_contiguous or not state.flags.writeable:
            raise ValueError("the hinge state is updated in place: pass a writeable C-contiguous array")
        return state

    def _client_rotations(self, rotations: np.ndarray, b: int) -> np.ndarray:
        j = self.source.num_joints
        rotations = np.ascontiguousarray(rotations, dtype=np.float64)
        if rotations.size != b * j * 4:
            raise ValueError(f"expected {b} frame(s) of {j} client joints, got rotations of shape {rotations.shape}")
        return rotations.reshape(b, j, 4)

    def _kernel_plan(self) -> None:
        """The rig as the plain arrays `retarget_kernels` takes, packed (`kernels.pack`)."""
        tree, plan = self._src_tree, self._plan
        par_s = np.full(len(tree.order), -1)
        for a, b, par in tree.levels:
            par_s[a:b] = par
        steps, nat, bone, hinge, m_loc_t, split_nat, reach = [], [], [], [], [], [], []
        for g in plan.groups:  # TwistPlan's groups, one joint a step
            for i, (j, p) in enumerate(zip(g["j"], g["p"])):
                limb = g["kind"] == "limb"
                split = g.get("split", (-1, np.eye(3)))
                steps.append(
                    (
                        kernels.KINDS.index(g["kind"]),
                        j,
                        p,
                        g["dir"][i] if "dir" in g else -1,
                        g["dir_c"][i] if limb else -1,
                        split[0],
                        self._hinge_slot[j] if limb else -1,
                        g["h"][i] if limb else -1,
                    )
                )
                split_nat.append(split[1])
                nat.append(g["nat"][i])
                bone.append(g["b"][i] if "b" in g else np.zeros(3))
                clavicle = g["kind"] == "clavicle"  # its limb slots hold (A | c) (`retarget_clavicle`)
                hinge.append(g["k"][i] if limb else g["ac"][i][:, 3] if clavicle else np.zeros(3))
                m_loc_t.append(g["m_loc_t"][i] if limb else g["ac"][i][:, :3] if clavicle else np.eye(3))
                reach.append(g["reach"][i] if limb else 0.0)
        nz = np.argwhere(self._vec_coef != 0)  # (v, t) entries, row by row
        bn_count = self._bn_parents.shape[0]
        ints = {
            "src_order": tree.order,
            "src_par_s": par_s,
            "fixed_par_s": self._fixed_par_s,
            "translated_par_s": self._translated_par_s,
            "vec_par_s": self._vec_par_s,
            "vec_nz": nz,
            "num_plain": self._num_plain,
            "lateral_j": plan.lateral,
            "step_i": steps,
            "bn_parents": self._bn_parents,
            "bn_order": self._bn_tree.order,
            "delta_j": np.unique(self._anc_bn_s[self._anc_bn_s < bn_count]),
            "anc_bn_s": self._anc_bn_s,
            "mapped_j": np.concatenate([self._mapped_nonroot, self._mapped_root]),
            "mapped_s": np.concatenate([self._mapped_s, self._mapped_root_s]),
            "mapped_par_s": np.concatenate([self._mapped_parents_s, np.full(len(self._mapped_root), -1)]),
            "drop_par": self._drop_par,
        }
        floats = {
            "fixed_off": self._fixed_off,
            "vec_off": self._vec_off,
            "vec_w": self._vec_coef[nz[:, 0], nz[:, 1]],
            "axes": self._axes,
            "m_tgt_t": self._m_tgt_t,
            "step_nat": nat,
            "step_b": bone,
            "step_k": hinge,
            "step_m_loc_t": m_loc_t,
            "bn_fixed_q": self._fixed_locals(),
            "drop_off": self._drop_off,
            "drop_ref": self._drop_ref,
            "step_split_nat": split_nat,
            "step_reach": reach,
        }
        self._k_plan = (
            *kernels.pack(ints, kernels.INT_PARTS, np.int64),
            *kernels.pack(floats, kernels.FLOAT_PARTS, np.float64),
        )

    def _fixed_locals(self) -> np.ndarray:
        """(22, 4) per BN joint, the local rotation it always gets; (-1, -1, -1, -1) if it moves."""
        out = np.full((self._bn_parents.shape[0], 4), -1.0)
        out[self._bn_parents < 0] = [0.0, 0.0, 0.0, 1.0]
        for g in self._plan.groups:
            if g["kind"] == "leaf":
                out[g["j"]] = mat_to_quat(g["nat"])
        return out
