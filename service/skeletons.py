"""Input skeletons: map a client's frames onto the model skeleton and the results back.

A session names a preset rig (`skeleton`, optionally with the `joints` its frames carry, in
their order) or sends a BVH header inline (`bvh_header`), plus optional `joint_map`, `units`,
`up` and `handedness`:
- the Bandai Namco skeleton (the models' own) passes through, reordered if its joints come in
  another order (extra joints pass through unchanged);
- any other humanoid (`models.motion.humanoid`: Mixamo, Unreal, Unity/VRM, SMPL, CMU, BVH
  exports, or anything whose names or `joint_map` give the body roles) is retargeted frame by
  frame on the way in and back onto the client's own rig on the way out
  (`models.motion.retarget_stream`), causally; the one thing it carries from frame to frame is
  the stream's hinge state, which the caller keeps (a session's `hinges`, a crowd row's) and
  passes to both directions (`FrameRetargeter.to_model`, `to_source`).
A rig that cannot be mapped is refused with a typed error naming what is missing; nothing of it
is applied.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from typing import Any, Protocol

import numpy as np

from models.motion import bvh as bvhio
from models.motion.bn_skeleton import missing_joints
from models.motion.humanoid import HumanoidRig, RigError, humanoid_rig, preset_rig, translated_joint
from models.motion.retarget_stream import FrameRetargeter
from models.motion.skeleton import Skeleton, skeleton_from_bvh

from . import rig_check
from .protocol import ProtocolError


class SkeletonAdapter(Protocol):
    """A client's rig <-> the model skeleton. The `_rows` forms take many frames at once, one row
    each ((n, 3) roots, (n, J, 4) rotations: a crowd's characters of one rig); row by row they
    give exactly what the one-frame forms give. `hinges`: the streams' retarget state, (n, 4, 4)
    (one-frame forms: (1, 4, 4); `FrameRetargeter.init_state`), which `to_model` updates in place
    and `from_model` reads for the same input frames."""

    joint_names: list[str]
    keeps_state: bool  # whether `hinges` is used (else any array, e.g. an empty one, will do)

    @property
    def num_joints(self) -> int: ...
    def to_model(
        self, root: np.ndarray, rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]: ...
    def from_model(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]: ...
    def to_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]: ...
    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]: ...
    def report(self) -> dict: ...


class _OneFrame:
    """The one-frame forms, as rows of one."""

    def to_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def to_model(self, root: np.ndarray, rotations: np.ndarray, hinges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out_root, out_rot = self.to_model_rows(root[None], rotations[None], hinges)
        return out_root[0], out_rot[0]

    def from_model(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        out_root, out_rot = self.from_model_rows(root[None], rotations[None], input_rotations[None], hinges)
        return out_root[0], out_rot[0]


class Reorder(_OneFrame):
    """Identity or a joint reordering between a client's joint order and the model's."""

    keeps_state = False

    def __init__(self, joint_names: list[str], model_skeleton: Skeleton) -> None:
        self.joint_names = list(joint_names)
        self.to_model_index = np.array([joint_names.index(n) for n in model_skeleton.names])
        self.identity = self.joint_names == list(model_skeleton.names)
        self.model_names = list(model_skeleton.names)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def to_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        return root, rotations if self.identity else rotations[:, self.to_model_index]

    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        if self.identity:
            return root, rotations
        out = input_rotations.copy()  # joints the model does not have pass through unchanged
        out[:, self.to_model_index] = rotations
        return root, out

    def report(self) -> dict:
        model = set(self.model_names)
        return {
            "preset": "bandai-namco",
            "retargeted": False,
            "mapping": {n: n for n in self.model_names},
            "unmapped": [n for n in self.joint_names if n not in model],
            "root_joint": "Hips",
        }


class Retarget(_OneFrame):
    """Any other humanoid: per-frame retargeting onto the model skeleton and back. The client's
    joint order may differ from the rig's internal parents-first order (`order`)."""

    rig_key: tuple | None = None  # its canonical rig (`_rig_key`), once built through the cache
    keeps_state = True

    def __init__(self, rig: HumanoidRig, joint_names: list[str] | None = None) -> None:
        self.rig = rig
        self.retargeter = FrameRetargeter(rig)
        internal = list(rig.skeleton.names)
        self.joint_names = list(joint_names) if joint_names is not None else internal
        self.order = None if self.joint_names == internal else np.array([self.joint_names.index(n) for n in internal])

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def to_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        return self.retargeter.to_model(root, rotations if self.order is None else rotations[:, self.order], hinges)

    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray, hinges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        inp = input_rotations if self.order is None else input_rotations[:, self.order]
        out_root, out_rot = self.retargeter.to_source(root, rotations, inp, hinges)
        if self.order is None:
            return out_root, out_rot
        back = np.empty_like(out_rot)
        back[:, self.order] = out_rot
        return out_root, back

    def report(self) -> dict:
        return {**self.rig.report(), "retargeted": True}


# rig problems -> the protocol's two skeleton codes; the message starts with the precise kind
_CODES = {
    "missing_roles": "unsupported_skeleton",
    "bad_topology": "unsupported_skeleton",
    "unsupported_skeleton": "unsupported_skeleton",
}


def rig_error(err: RigError) -> ProtocolError:
    """A `RigError` as the typed, fatal protocol error: `unsupported_skeleton` for a rig that is
    not a usable humanoid, `bad_skeleton` for a malformed header, joint list or option; the
    message names every missing role or broken link."""
    return ProtocolError(_CODES.get(err.code, "bad_skeleton"), f"{err.code}: {err.message}", fatal=True)


def _rig_key(skeleton: Skeleton, translated: int | None, options: dict) -> tuple:
    """What makes two rigs the same rig: names, hierarchy, offsets, the translated joint and the
    options; not the header's spelling (spacing, number format, channel order, MOTION rows)."""
    return (
        tuple(skeleton.names),
        np.asarray(skeleton.parents, np.int64).tobytes(),
        np.asarray(skeleton.offsets, np.float64).tobytes(),
        np.asarray(skeleton.end_sites, np.float64).tobytes(),
        translated,
        json.dumps(options, sort_keys=True),
    )


# canonical rig -> its adapter; and the texts seen -> that adapter (a repeat costs a dict lookup
# on the event loop, with no worker hop): many sessions and characters bring the same rig
_BY_RIG: OrderedDict[tuple, Retarget] = OrderedDict()
_BY_TEXT: OrderedDict[tuple, SkeletonAdapter] = OrderedDict()
_CACHE_SIZE = 256
_cache_lock = threading.Lock()  # builds run on worker threads


def _remember(cache: OrderedDict, key: tuple, value: Any) -> Any:
    if cache is _BY_RIG:
        value.rig_key = key
    with _cache_lock:
        cache[key] = value
        cache.move_to_end(key)
        while len(cache) > _CACHE_SIZE:
            cache.popitem(last=False)
    return value


def _recall(cache: OrderedDict, key: tuple) -> Any:
    with _cache_lock:
        value = cache.get(key)
        if value is not None:
            cache.move_to_end(key)
        return value


def checked_build(rig: HumanoidRig, joints: list[str] | None = None) -> Retarget:
    """The retargeter for a checked rig; whatever its set-up trips over is the rig's fault
    (a typed `degenerate_rig`), never an exception that escapes to the connection."""
    rig_check.check_rig(rig)
    try:
        with np.errstate(divide="raise", over="raise", invalid="raise", under="ignore"):
            adapter = Retarget(rig, joints)
    except (ArithmeticError, ValueError, FloatingPointError, IndexError) as exc:
        raise RigError("degenerate_rig", f"the retargeter cannot be set up for this rig ({exc})") from None
    r = adapter.retargeter
    if not (np.isfinite(r.scale) and np.isfinite(r.vertical_offset)):
        raise RigError("degenerate_rig", "the rig's scale or standing height is not finite")
    return adapter


def _from_header(parsed: bvhio.BvhFile, skeleton: Skeleton, options: dict) -> Retarget:
    """A custom rig's adapter (its header parsed and checked), through the canonical-rig cache."""
    if "joints" in options:
        raise RigError(
            "bad_skeleton", "give 'joints' with a preset 'skeleton', not with 'bvh_header' (its order is the header's)"
        )
    translated = translated_joint(parsed, skeleton, options.get("joint_map"))
    key = _rig_key(skeleton, translated, options)
    cached = _recall(_BY_RIG, key)
    if cached is not None:
        return cached
    rig = humanoid_rig(skeleton, **options, translated=translated)
    return _remember(_BY_RIG, key, checked_build(rig))


def rig_from_header(bvh_header: str, **options) -> HumanoidRig:
    """`humanoid.rig_from_bvh` within the limits (`service.rig_check`), checked before the match."""
    parsed, skeleton = _parse(bvh_header)
    return humanoid_rig(skeleton, **options, translated=translated_joint(parsed, skeleton, options.get("joint_map")))


def _parse(bvh_header: str) -> tuple[bvhio.BvhFile, Skeleton]:
    """The header's hierarchy, within the limits (`service.rig_check`), or a typed `RigError`."""
    rig_check.check_header(bvh_header)
    text = bvh_header.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.0333333\n"
    try:
        parsed = bvhio.parse(text, "bvh_header")
    except bvhio.BvhError as exc:
        raise RigError("bad_skeleton", str(exc)) from None
    skeleton = skeleton_from_bvh(parsed)[0]
    rig_check.check_skeleton(skeleton)
    return parsed, skeleton


def _as_model_world(options: dict) -> bool:
    """No option moves the rig off the model's own world (a left-handed, Z-up or metre BN rig is retargeted)."""
    return (
        not options.get("joint_map")
        and options.get("handedness", "right") == "right"
        and options.get("up") in (None, "y")
        and options.get("units") in (None, "cm")
    )


def _is_model_skeleton(names: list[str], model_skeleton: Skeleton, options: dict) -> bool:
    return not missing_joints(names, model_skeleton.names) and _as_model_world(options)


def _adapter(
    skeleton: str | None, bvh_header: str | None, model_skeleton: Skeleton, joints: list[str] | None, options: dict
) -> SkeletonAdapter:
    if joints is not None:
        rig_check.check_names(joints)
    if bvh_header is not None:
        parsed, parsed_skeleton = _parse(bvh_header)
        names = list(parsed_skeleton.names)
        if joints is None and _is_model_skeleton(names, model_skeleton, options):  # no retargeter needed
            return Reorder(names, model_skeleton)
        return _from_header(parsed, parsed_skeleton, {**options, **({"joints": joints} if joints is not None else {})})
    if skeleton == "bandai-namco" and _as_model_world(options):
        names = list(joints) if joints is not None else list(model_skeleton.names)
        missing = [n for n in model_skeleton.names if n not in names]
        if missing or len(set(names)) != len(names):
            raise ProtocolError(
                "bad_skeleton",
                f"joints must list every Bandai Namco joint once (missing: {', '.join(missing) or 'none'})",
                fatal=True,
            )
        return Reorder(names, model_skeleton)
    if skeleton in (None, "custom"):
        raise ProtocolError("unsupported_skeleton", "give a preset 'skeleton' or a 'bvh_header'", fatal=True)
    key = ("preset", skeleton, json.dumps({**options, "joints": joints}, sort_keys=True))
    cached = _recall(_BY_RIG, key)
    if cached is not None:
        return cached
    return _remember(_BY_RIG, key, checked_build(preset_rig(skeleton, joints=joints, **options), joints))


def _text_key(
    skeleton: str | None, bvh_header: str | None, model_skeleton: Skeleton, joints: list[str] | None, options: dict
) -> tuple:
    return (skeleton, bvh_header, tuple(model_skeleton.names), json.dumps([joints, options], sort_keys=True))


def adapter_for(
    skeleton: str | None, bvh_header: str | None, model_skeleton: Skeleton, joints: list[str] | None = None, **options
) -> SkeletonAdapter:
    """The adapter for a start message's rig; raises `ProtocolError` (fatal, typed) for a rig
    that cannot be mapped, before anything is set up. Synchronous and up to a few hundred ms for
    a large rig: a connection calls `rig_builds.RigBuilds.adapter`, which runs it off the event loop."""
    text_key = _text_key(skeleton, bvh_header, model_skeleton, joints, options)
    cached = _recall(_BY_TEXT, text_key)
    if cached is not None:
        return cached
    try:
        adapter = _adapter(skeleton, bvh_header, model_skeleton, joints, options)
    except RigError as err:
        raise rig_error(err) from None
    return _remember(_BY_TEXT, text_key, adapter)


def adopt(
    adapter: SkeletonAdapter,
    skeleton: str | None,
    bvh_header: str | None,
    model_skeleton: Skeleton,
    joints: list[str] | None = None,
    **options,
) -> SkeletonAdapter:
    """An adapter `adapter_for` built elsewhere (a child process, `service.rig_builds`) for these
    fields, remembered here as if built here: the one already built for the same rig in another
    spelling is kept and answered instead, so many characters on one rig share one adapter."""
    key = getattr(adapter, "rig_key", None)
    if key is not None:
        adapter = _recall(_BY_RIG, key) or _remember(_BY_RIG, key, adapter)
    text_key = _text_key(skeleton, bvh_header, model_skeleton, joints, options)
    return _remember(_BY_TEXT, text_key, adapter)


def cached_adapter(
    skeleton: str | None, bvh_header: str | None, model_skeleton: Skeleton, joints: list[str] | None = None, **options
) -> SkeletonAdapter | None:
    """The adapter `adapter_for` gave for exactly these fields before, if it still has it."""
    text_key = _text_key(skeleton, bvh_header, model_skeleton, joints, options)
    return _recall(_BY_TEXT, text_key)


def warm() -> None:
    """Load (or, on a fresh machine, compile: ~15 s) the per-frame retargeting kernels before the
    first custom-rig session rather than on its first frame: building one retargeter runs both
    directions while it measures its standing offset."""
    FrameRetargeter(preset_rig("cmu"))
