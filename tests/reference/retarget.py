"""`FrameRetargeter.to_model` and `to_source` in numpy, batched over frames and over the joints of
one tree depth: the reference the compiled kernels (`models/motion/retarget_kernels.py`) are
tested against (`tests/test_retarget_kernels.py`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from models.motion.retarget import HINGE_FALLBACK, HINGE_PRIOR, TWIST_SHARE, TwistPlan, _frame, _unit
from models.motion.retarget_stream import FrameRetargeter, _Tree
from models.motion.rotations import matrix_to_quat as mat_to_quat
from models.motion.rotations import quat_to_matrix as quat_to_mat


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) by `angle` (...) about the unit `axis` (3,) (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    a = np.asarray(angle)[..., None, None]
    return np.eye(3) + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def twist_angle(m: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The twist (...) about the unit `axis` (3,) of rotation matrices m (..., 3, 3), radians in
    (-pi, pi]: 2 atan2(q_v . axis, q_w) for m's quaternion q with q_w >= 0, written on the matrix
    (q_v 4 q_w is the skew part's vector, 4 q_w^2 is 1 + trace)."""
    v = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1)
    return 2.0 * np.arctan2(v @ axis, 1.0 + np.trace(m, axis1=-2, axis2=-1))


def _swing_mats(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations (..., 3, 3) taking unit vectors a to unit vectors b (Rodrigues without
    trigonometry: I + [v]x + [v]x^2 / (1 + c), v = a x b, c = a . b). Exactly opposite vectors
    (a bone pointing exactly away from its natural direction in its parent's frame; not met in
    walks) get the half turn about an axis perpendicular to a."""
    v, c = np.cross(a, b), np.sum(a * b, axis=-1)
    flip = c < -1.0 + 1e-9
    if np.any(flip):  # replace v by a unit axis perpendicular to a; the formula then gives the half turn
        perp = np.cross(a, np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
        v = np.where(flip[..., None], _unit(perp), v)
        c = np.where(flip, -1.0 + 1e-12, c)
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    scale = np.where(flip, 1.0, 1.0 / (1.0 + c))[..., None, None]
    m = np.eye(3) + np.where(flip[..., None, None], 0.0, k) + (k @ k) * scale
    return m


Fallback = Callable[[int, int, np.ndarray, np.ndarray], np.ndarray]


def bn_globals(plan: TwistPlan, dirs: np.ndarray, lateral: np.ndarray, fallback: Fallback | None = None) -> np.ndarray:
    """BN world rotation matrices (B, J, 3, 3) from unit bone directions `dirs` (B, K, 3),
    columns as `segments`, and the two-vector joints' world rotations `lateral` (B, 2, 3, 3).
    `fallback(joint, hinge row, normal (B, 3), natural axis (B, 3))`: a limb's fallback axis
    (`_hinge_fallback`); None: the natural axis."""
    b = dirs.shape[0]
    dirs = dirs.copy()  # a limb's lower bone is laid into its hinge plane below
    gb = np.empty((b, plan.num_joints, 3, 3))
    gb[:] = np.eye(3)  # joint_Root
    gb[:, plan.lateral] = lateral
    for g in plan.groups:
        gp = gb[:, g["p"]]
        if g["kind"] == "leaf":
            gb[:, g["j"]] = gp @ g["nat"]
            continue
        base = gp @ g["nat"]  # natural local rotation under the BN parent
        d = dirs[:, g["dir"]]
        if g["kind"] == "clavicle":  # d is the upper arm's direction, mapped in the chest's frame
            local = (np.swapaxes(gp, -1, -2) @ d[..., None])[..., 0]
            d = _unit((gp @ (np.einsum("kij,bkj->bki", g["ac"][..., :3], local) + g["ac"][..., 3])[..., None])[..., 0])
        rot = _swing_mats((base @ g["b"][..., None])[..., 0], d) @ base
        if g["kind"] == "limb":
            lower = dirs[:, g["dir_c"]]
            natural = (rot @ g["k"][..., None])[..., 0]
            normal = np.cross(d, lower)  # its sign is the bend's: cross(upper, lower) for a flexed limb
            if fallback is not None:
                for i, (j, h) in enumerate(zip(g["j"], g["h"], strict=True)):
                    natural[:, i] = fallback(int(j), int(h), normal[:, i], natural[:, i])
            axis = np.linalg.norm(normal, axis=-1, keepdims=True) * normal + HINGE_FALLBACK**2 * natural
            frame = _frame(d, axis)
            rot = frame @ g["m_loc_t"]
            # the hinge child bends about the hinge axis alone; the limb turns to keep its end's direction
            hinge = frame[..., :, 1]
            laid = lower - np.sum(lower * hinge, axis=-1, keepdims=True) * hinge
            laid = laid / np.linalg.norm(laid, axis=-1, keepdims=True)
            reach = g["reach"][:, None]
            turn = _swing_mats(_unit(d + reach * laid), _unit(d + reach * lower))
            rot = turn @ rot
            dirs[:, g["dir_c"]] = (turn @ laid[..., None])[..., 0]
        if "split" in g:  # take a share of the two-vector child's twist about the bone
            c, nat_c = g["split"]
            axis = g["b"][0]
            dev = np.swapaxes(rot[:, 0], -1, -2) @ gb[:, c] @ nat_c.T  # the child's local, off natural
            rot = rot @ _axis_angle(axis, TWIST_SHARE * twist_angle(dev, axis))[:, None]
        gb[:, g["j"]] = rot
    return gb


def tree_fk(tree: _Tree, local: np.ndarray) -> np.ndarray:
    """World rotation matrices (B, K, 3, 3) of the kept joints, in `order`, from all the
    joints' local matrices (B, J, 3, 3)."""
    g = local[:, tree.order]
    for a, b, par in tree.levels:
        g[:, a:b] = g[:, par] @ g[:, a:b]
    return g


def _vectors(fr: FrameRetargeter, gs: np.ndarray) -> np.ndarray:
    """The vectors read from a frame (B, V, 3) in BN's world, from client world rotation
    matrices (tree slots): segments, two-vector joints' (up, side), hips -> foot points."""
    vec = (gs[:, fr._vec_par_s] @ fr._vec_off)[..., 0]  # (B, T, 3)
    return (fr._vec_coef @ vec) @ fr._axes.T


def _drop(fr: FrameRetargeter, vec: np.ndarray, gb: np.ndarray) -> np.ndarray:
    """(B,) how far the root rises so that BN's lowest foot point is no lower than the client's.

    Bones are laid along the client's segments, so with other limb proportions BN's feet do
    not land where the client's do: on a rig with a longer shin than BN's (thigh x0.75, shin
    x1.25), a kneeling client's BN feet sank 6.8 cm into the floor. Per frame, each foot point
    (toes, ankles) is taken below the hips and above its own standing height (`_drop_ref`;
    toes against toes, ankles against ankles, as the rigs' feet differ), the client's scaled;
    when BN's lowest is lower than the client's, the root rises by the difference. It never
    sinks: a client's toe pressed into its floor (CMU 131_02's, by 5 cm) does not pull BN's
    under, and a sitting client's BN feet may float as before. `vec` from `_vectors`, `gb`
    BN world rotations (B, 22, 3, 3)."""
    client = fr.scale * (vec[:, vec.shape[1] - len(fr._drop_kind) :, 1] - fr._drop_ref[0]).min(axis=1)
    gbp = np.concatenate([gb, np.zeros_like(gb[:, :1])], axis=1)  # parent -1 (padding): a zero matrix
    bn = np.sum((gbp[:, fr._drop_par] @ fr._drop_off[..., None])[..., 1, 0], axis=-1)
    return np.maximum(client - (bn - fr._drop_ref[1]).min(axis=1), 0.0)


def _hinge_fallback(fr: FrameRetargeter, gs: np.ndarray, hinges: np.ndarray, fold: bool) -> Fallback:
    """The kernels' `_hinge_fallback` over frames: hinges (B, H, 4) one stream per row, or (1, H, 4)
    one stream whose successive frames the rows are (running sums over them); updated in place
    when `fold`."""

    def fallback(j: int, h: int, normal: np.ndarray, natural: np.ndarray) -> np.ndarray:
        g = fr._axes @ gs[:, fr._hinge_slot[j]]  # the client joint's frame in BN's world (B, 3, 3)
        acc = np.broadcast_to(hinges[:, h], (len(normal), 4)).copy()
        if fold:
            s2 = np.sum(normal * normal, axis=-1, keepdims=True)
            v = s2 * normal
            fresh = hinges[:, h, 3] == 0.0
            v[: len(fresh)][fresh] += HINGE_PRIOR * natural[: len(fresh)][fresh]  # seeds its stream's first frame
            step = np.concatenate([(np.swapaxes(g, -1, -2) @ v[..., None])[..., 0], s2], axis=-1)
            step[: len(fresh), 3] += np.where(fresh, HINGE_PRIOR, 0.0)
            acc = hinges[:, h] + (np.cumsum(step, axis=0) if len(hinges) == 1 else step)
            hinges[:, h] = acc[-1] if len(hinges) == 1 else acc
        k = np.linalg.norm(acc[:, :3], axis=-1, keepdims=True)
        client = (g @ (acc[:, :3] / np.where(k > 0, k, 1.0))[..., None])[..., 0]
        mix = natural + client
        m = np.linalg.norm(mix, axis=-1, keepdims=True)
        return np.where((k > 0) & (m > 1e-9), mix / np.where(m > 1e-9, m, 1.0), natural)

    return fallback


def _bn_globals(
    fr: FrameRetargeter, gs: np.ndarray, vec: np.ndarray | None = None, fallback: Fallback | None = None
) -> np.ndarray:
    """BN world rotation matrices (B, 22, 3, 3) from client world rotation matrices (tree slots)."""
    b = gs.shape[0]
    vec = _vectors(fr, gs) if vec is None else vec
    k = fr._num_plain
    dirs = vec[:, :k] / np.sqrt(np.sum(vec[:, :k] ** 2, axis=-1, keepdims=True))
    lat = vec[:, k : vec.shape[1] - len(fr._drop_kind)].reshape(b, -1, 2, 3)
    return bn_globals(fr._plan, dirs, _frame(lat[:, :, 0], lat[:, :, 1]) @ fr._m_tgt_t, fallback)


def _source_globals(fr: FrameRetargeter, rotations: np.ndarray) -> np.ndarray:
    return tree_fk(fr._src_tree, quat_to_mat(rotations))


def _hips_terms(fr: FrameRetargeter, gs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(c (B, 3), Gp (B, 3, 3)): the client hips' world position is c + Gp @ root."""
    b = gs.shape[0]
    g = np.concatenate([gs, np.broadcast_to(np.eye(3), (b, 1, 3, 3))], axis=1)  # slot -1: identity
    c = np.sum((g[:, fr._fixed_par_s] @ fr._fixed_off[..., None])[..., 0], axis=1)
    return c, g[:, fr._translated_par_s]


def to_model(
    fr: FrameRetargeter, root: np.ndarray, rotations: np.ndarray, state: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """`to_model` in numpy (batched over frames and tree depths): the reference the compiled
    kernel is tested against.

    root (B, 3): the translation of the client's translated joint (`HumanoidRig.translated`:
    the hips, or the root above them); rotations (B, Js, 4): client local quaternions (xyzw).
    Returns (Hips translation (B, 3), BN local rotations (B, 22, 4), w >= 0). Every other BN
    translation is the BN skeleton's offset. state: as `FrameRetargeter.to_model`'s."""
    root = np.asarray(root, dtype=np.float64).reshape(-1, 3)
    gs = _source_globals(fr, np.asarray(rotations, dtype=np.float64).reshape(root.shape[0], -1, 4))
    c, gp = _hips_terms(fr, gs)
    hips = ((c + (gp @ root[..., None])[..., 0]) @ fr._axes.T) * fr.scale
    vec = _vectors(fr, gs)
    hinges = fr.init_state() if state is None else state
    gb = _bn_globals(fr, gs, vec, _hinge_fallback(fr, gs, hinges, True))
    hips[:, 1] += fr.vertical_offset + _drop(fr, vec, gb)
    local = gb.copy()
    local[:, 1:] = np.swapaxes(gb[:, fr._bn_parents[1:]], -1, -2) @ gb[:, 1:]
    return hips, mat_to_quat(local)


def to_source(
    fr: FrameRetargeter,
    root_bn: np.ndarray,
    rotations_bn: np.ndarray,
    source_rotations: np.ndarray,
    state: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`to_source` in numpy: the reference the compiled kernel is tested against.

    root_bn (B, 3): BN Hips translation; rotations_bn (B, 22, 4): BN local quaternions;
    source_rotations (B, Js, 4): the client's own local rotations for the same frame(s)
    (unmapped joints keep these; they also fix the twist the BN change is applied to).
    state: as `FrameRetargeter.to_source`'s.
    Returns (client root translation (B, 3), client local rotations (B, Js, 4))."""
    root_bn = np.asarray(root_bn, dtype=np.float64).reshape(-1, 3)
    b = root_bn.shape[0]
    source_rotations = np.asarray(source_rotations, dtype=np.float64).reshape(b, -1, 4)
    gbn = tree_fk(fr._bn_tree, quat_to_mat(np.asarray(rotations_bn, dtype=np.float64).reshape(b, -1, 4)))
    gsc = _source_globals(fr, source_rotations)
    hinges = fr.init_state() if state is None else state
    gbc = _bn_globals(fr, gsc, fallback=_hinge_fallback(fr, gsc, hinges, state is None))
    delta = gbn[:, fr._bn_tree.pos] @ np.swapaxes(gbc, -1, -2)  # (B, 22, 3, 3), BN joint order, BN world
    delta = fr._axes.T @ delta @ fr._axes  # the same change in the client's world
    delta = np.concatenate([delta, np.broadcast_to(np.eye(3), (b, 1, 3, 3))], axis=1)
    g_new = delta[:, fr._anc_bn_s] @ gsc  # every client joint turns with its mapped ancestor's BN joint
    out = source_rotations.copy()  # unmapped joints keep the client's local rotations
    if len(fr._mapped_nonroot):
        out[:, fr._mapped_nonroot] = mat_to_quat(
            np.swapaxes(g_new[:, fr._mapped_parents_s], -1, -2) @ g_new[:, fr._mapped_s]
        )
    if len(fr._mapped_root):
        out[:, fr._mapped_root] = mat_to_quat(g_new[:, fr._mapped_root_s])
    hips = root_bn.copy()
    hips[:, 1] -= fr.vertical_offset + _drop(fr, _vectors(fr, g_new), gbn[:, fr._bn_tree.pos])
    hips = (hips / fr.scale) @ fr._axes  # client world (axes are orthogonal: inverse = transpose)
    c, gp = _hips_terms(fr, gsc)  # the chain above the hips is unchanged
    return (np.swapaxes(gp, -1, -2) @ (hips - c)[..., None])[..., 0], out
