"""Causal, per-frame retargeting between a client's CMU skeleton and the Bandai Namco (BN) model skeleton.

`retarget.retarget` works on whole clips: it resamples and shifts the root vertically by a
percentile of the clip's toe heights, both of which look at the whole clip. A live stream has one
frame at a time, so `FrameRetargeter` does the same per-frame mapping with everything else fixed
up front:

* the per-joint mapping is `retarget.TwistPlan`, the very code `retarget` runs, and the leg-length
  scale is the same;
* the vertical offset is a constant from rest geometry (see `FrameRetargeter.vertical_offset`),
  so `to_model` equals `retarget(motion, fps=motion.fps)` frame by frame up to one constant
  shift of the Hips height.

`to_source` is the inverse, a (stylised) BN frame back onto the client's skeleton. Every BN joint
j (but `joint_Root`) gives a "delta" D_j = G_bn_new[j] G_bn_client[j]^-1, the change of its global
rotation from the BN pose the client's own frame maps to (`to_model` of `source_rotations`) to
the one given. Each source joint k gets G_new[k] = D_{j(k)} G_client[k], j(k) the BN joint of
k's nearest mapped ancestor-or-self. So

* a mapped CMU joint with a single-bone BN counterpart is turned by the change of its BN joint:
  `to_model` lays the BN bone exactly along the client's bone, so after the turn the client's
  bone points where the new BN bone points; the twist about it is the client's own, turned by BN's
  change of twist (BN twists come from the BN parent / limb plane, not from the client);
* the two-vector joints (Hips, chest) are turned by the BN delta, which puts their spine bone and
  hip / shoulder line where BN has them (using the client's own unmapped joints in between);
* unmapped joints (LHipJoint, LowerBack, Neck / lowerneck, fingers, thumbs) keep the client's
  local rotations;

and `to_source(*to_model(root, rot), rot) == (root, rot)` up to float rounding.

Internally everything runs on rotation matrices batched over frames and over joints of one tree
depth (one `matmul` per depth level), so a single frame takes a few hundred microseconds.
"""

from __future__ import annotations


import numpy as np

from .retarget import (_LATERAL, _PRIMARY_CHILD, _SOURCE_LATERAL, CMU_TO_BN, Rig, TwistPlan, _drivers, _frame,
                       default_rig, leg_length, source_variant)
from .rotations import matrix_to_quat as mat_to_quat
from .rotations import quat_to_matrix as quat_to_mat
from .skeleton import Skeleton, fk


# --------------------------------------------------------------------------- small numpy kernels


_EPS = np.zeros((3, 3, 3))  # Levi-Civita: cross(a, b)_i = eps[j, k, i] a_j b_k
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0
_EPS = _EPS.reshape(9, 3)


def _frame_fast(primary: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """`retarget._frame` (columns: primary, lateral made orthogonal, their cross) in few numpy calls."""
    e1 = primary / np.sqrt(np.sum(primary * primary, axis=-1, keepdims=True))
    e2 = lateral - np.sum(lateral * e1, axis=-1, keepdims=True) * e1
    e2 = e2 / np.sqrt(np.sum(e2 * e2, axis=-1, keepdims=True))
    e3 = (e1[..., :, None] * e2[..., None, :]).reshape(e1.shape[:-1] + (9,)) @ _EPS
    return np.stack([e1, e2, e3], axis=-1)


class _Tree:
    """FK over a joint subset, one `matmul` per tree depth: the kept joints are stored depth by
    depth (`order`), so each level is a contiguous slice and only its parents are gathered."""

    def __init__(self, parents: np.ndarray, needed: np.ndarray | None = None):
        parents = np.asarray(parents)
        n = len(parents)
        depth = np.zeros(n, int)
        for j, p in enumerate(parents):
            depth[j] = depth[p] + 1 if p >= 0 else 0
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
        self.levels = [(int(np.searchsorted(d, k)), int(np.searchsorted(d, k, "right")),
                        self.pos[parents[self.order[d == k]]]) for k in range(1, int(d.max(initial=0)) + 1)]
        self.roots = int(np.searchsorted(d, 0, "right"))

    def fk(self, local: np.ndarray) -> np.ndarray:
        """World rotation matrices (B, K, 3, 3) of the kept joints, in `order`, from all the
        joints' local matrices (B, J, 3, 3)."""
        g = local[:, self.order]
        for a, b, par in self.levels:
            g[:, a:b] = g[:, par] @ g[:, a:b]
        return g


def _path_terms(skeleton: Skeleton, a: int, b: int) -> list[tuple[int, float]]:
    """(joint k, sign) with pos[b] - pos[a] = sum sign * G[parent k] @ offset[k] (through the
    lowest common ancestor); zero-length offsets are dropped."""
    def up(j: int) -> list[int]:
        chain = []
        while j >= 0:
            chain.append(j)
            j = int(skeleton.parents[j])
        return chain

    ca, cb = up(a), up(b)
    common = next(j for j in ca if j in cb)
    terms = [(k, 1.0) for k in cb[:cb.index(common)]] + [(k, -1.0) for k in ca[:ca.index(common)]]
    return [(k, s) for k, s in terms if np.linalg.norm(skeleton.offsets[k]) > 1e-9]


# --------------------------------------------------------------------------- the retargeter


class FrameRetargeter:
    """Per-frame CMU <-> BN retargeting for one client skeleton (either CMU naming variant).

    Stateless after construction: the output for a frame depends on that frame only, and every
    method is vectorised over a leading batch axis B (frames or sessions).

    `source_floor`: the height (source units) at which the client's toe joints touch the ground;
    default `rig.floor / scale`, i.e. the same toe-joint height in leg lengths as the BN data
    (~0.75 CMU units; the CMU files show 0.7-1.1, the Xia files about -0.2, as Xia's floor sits
    lower). `vertical_offset` overrides the derived Hips height shift altogether.
    """

    def __init__(self, source: Skeleton, rig: Rig | None = None, source_floor: float | None = None,
                 vertical_offset: float | None = None):
        rig = default_rig() if rig is None else rig
        self.source, self.rig = source, rig
        sk = rig.skeleton
        self.variant = source_variant(source)
        smap = CMU_TO_BN[self.variant]
        if source.parents[source.index(smap["Hips"])] >= 0 or sk.parents[sk.index("Hips")] < 0:
            raise ValueError("expected Hips to be the source root and to have a parent (joint_Root) in BN")
        self._bn_tree = _Tree(sk.parents)
        self._bn_unorder = self._bn_tree.pos  # slot -> joint order
        self._src_parents = np.asarray(source.parents)
        self._bn_parents = np.asarray(sk.parents)
        self._bn_hips = sk.index("Hips")
        self._src_root = source.index(smap["Hips"])

        # Two-vector joints (Hips, Chest): from source vectors, here. Every other joint: `TwistPlan`
        # (bone onto the source bone, twist from the BN parent / the limb plane), on tree slots.
        drivers = _drivers(source, smap)
        # vectors: (lateral 0 up, lateral 0 side, lateral 1 up, ...) as signed sums of G[parent k] offset[k]
        terms: list[list[tuple[int, float]]] = []
        m_tgt = []
        for name, (tl, tr) in _LATERAL.items():
            child = _PRIMARY_CHILD[name]
            sl, sr = _SOURCE_LATERAL[name]
            src = lambda n: source.index(smap[n])  # noqa: E731
            terms.append(_path_terms(source, src(name), src(child)))
            terms.append(_path_terms(source, src(sr), src(sl)))
            off = lambda n: sk.offsets[sk.index(n)]  # noqa: E731
            m_tgt.append(_frame(off(child), off(tl) - off(tr)))
        flat = sorted({k for t in terms for k, _ in t})
        self._vec_par = self._src_parents[flat]
        self._vec_off = source.offsets[flat][:, :, None]  # (T, 3, 1)
        self._vec_coef = np.zeros((len(terms), len(flat)))
        for v, t in enumerate(terms):
            for k, s in t:
                self._vec_coef[v, flat.index(k)] += s
        self._m_tgt_t = np.swapaxes(np.stack(m_tgt), -1, -2)  # (L, 3, 3), transposed

        # to_source: each source joint takes the delta of the BN joint of its nearest mapped ancestor
        mapped = {source.index(s): sk.index(b) for b, s in smap.items()}
        anc = np.zeros(source.num_joints, int)
        for k in range(source.num_joints):
            j = k
            while j not in mapped:
                j = int(source.parents[j])
            anc[k] = mapped[j]
        self._anc_bn = anc
        self._mapped_nonroot = np.array([k for k in sorted(mapped) if source.parents[k] >= 0])
        self._mapped_parents = self._src_parents[self._mapped_nonroot]
        needed = np.unique(np.concatenate([[self._src_root], list(drivers.values()), self._vec_par, self._mapped_nonroot, self._mapped_parents]))
        tree = self._src_tree = _Tree(source.parents, needed)  # source world rotations live in tree slots
        self._plan = TwistPlan(rig, source, slots=tree.pos)
        self._vec_par_s = tree.pos[self._vec_par]
        self._anc_bn_s = anc[tree.order]
        self._mapped_s, self._mapped_parents_s = tree.pos[self._mapped_nonroot], tree.pos[self._mapped_parents]
        self._root_s = int(tree.pos[self._src_root])

        self.scale = leg_length(sk) / leg_length(source, self.variant)
        self.source_floor = rig.floor / self.scale if source_floor is None else float(source_floor)
        self.vertical_offset = self._rest_offset() if vertical_offset is None else float(vertical_offset)

    # ----------------------------------------------------------------------- internals

    def _bn_globals(self, gs: np.ndarray) -> np.ndarray:
        """BN world rotation matrices (B, 22, 3, 3) from source world rotation matrices."""
        b = gs.shape[0]
        vec = (gs[:, self._vec_par_s] @ self._vec_off)[..., 0]  # (B, T, 3)
        vec = (self._vec_coef @ vec).reshape(b, -1, 2, 3)
        return self._plan.bn_globals(gs, _frame_fast(vec[:, :, 0], vec[:, :, 1]) @ self._m_tgt_t)

    def _source_globals(self, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        local = quat_to_mat(rotations)
        return local, self._src_tree.fk(local)

    def _local_bn(self, rotations: np.ndarray) -> np.ndarray:
        """BN local rotations (B, 22, 4) for source local rotations (B, Js, 4)."""
        _, gs = self._source_globals(rotations)
        gb = self._bn_globals(gs)
        local = gb.copy()
        local[:, 1:] = np.swapaxes(gb[:, self._bn_parents[1:]], -1, -2) @ gb[:, 1:]
        return mat_to_quat(local)

    def _rest_offset(self) -> float:
        """Hips height shift (BN hips y = scale * source hips y + offset), from rest geometry only:
        with the source in its rest pose (every rotation zero) and its toes at `source_floor`,
        the BN skeleton in the same pose has its toes at `rig.floor`."""
        sk, src = self.rig.skeleton, self.source
        smap = CMU_TO_BN[self.variant]
        t_src = float(src.rest_positions()[[src.index(smap[f"Toes_{s}"]) for s in "LR"], 1].mean())  # toes below hips
        rest = np.zeros((1, src.num_joints, 4))
        rest[..., 3] = 1.0
        trans = np.broadcast_to(sk.offsets, (1, sk.num_joints, 3)).copy()
        trans[:, self._bn_hips] = 0.0
        _, pos = fk(self._local_bn(rest), trans, sk.parents)
        t_bn = float(pos[0, [sk.index("Toes_L"), sk.index("Toes_R")], 1].mean())
        # source hips at source_floor - t_src  ->  BN hips at rig.floor - t_bn
        return self.rig.floor - t_bn - self.scale * (self.source_floor - t_src)

    # ----------------------------------------------------------------------- API

    def to_model(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Source frame(s) -> BN frame(s).

        root (B, 3): the source root (Hips) translation; rotations (B, Js, 4): source local
        quaternions (xyzw). Returns (Hips translation (B, 3), BN local rotations (B, 22, 4),
        w >= 0). Every other BN translation is the BN skeleton's offset."""
        root = np.asarray(root, dtype=np.float64).reshape(-1, 3)
        local = self._local_bn(np.asarray(rotations, dtype=np.float64).reshape(root.shape[0], -1, 4))
        hips = root * self.scale
        hips[:, 1] += self.vertical_offset
        return hips, local

    def to_source(self, root_bn: np.ndarray, rotations_bn: np.ndarray, source_rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """BN frame(s) -> source frame(s) on the client's skeleton.

        root_bn (B, 3): BN Hips translation; rotations_bn (B, 22, 4): BN local quaternions;
        source_rotations (B, Js, 4): the client's own local rotations for the same frame(s)
        (unmapped joints keep these; the two-vector joints use them for their in-between joints).
        Returns (source root translation (B, 3), source local rotations (B, Js, 4))."""
        root_bn = np.asarray(root_bn, dtype=np.float64).reshape(-1, 3)
        b = root_bn.shape[0]
        source_rotations = np.asarray(source_rotations, dtype=np.float64).reshape(b, -1, 4)
        gbn = self._bn_tree.fk(quat_to_mat(np.asarray(rotations_bn, dtype=np.float64).reshape(b, -1, 4)))
        _, gsc = self._source_globals(source_rotations)
        gbc = self._bn_globals(gsc)
        delta = gbn[:, self._bn_unorder] @ np.swapaxes(gbc, -1, -2)  # (B, 22, 3, 3), BN joint order
        g_new = delta[:, self._anc_bn_s] @ gsc  # every source joint turns with its mapped ancestor's BN joint
        out = source_rotations.copy()  # unmapped joints keep the client's local rotations
        out[:, self._mapped_nonroot] = mat_to_quat(np.swapaxes(g_new[:, self._mapped_parents_s], -1, -2) @ g_new[:, self._mapped_s])
        out[:, self._src_root] = mat_to_quat(g_new[:, self._root_s])
        src_root = root_bn.copy()
        src_root[:, 1] -= self.vertical_offset
        return src_root / self.scale, out
