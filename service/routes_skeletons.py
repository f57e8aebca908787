"""`POST /v1/skeletons`: check a rig before streaming it, and see how it maps.

The body names a preset (`skeleton`, optionally with `joints`) or carries a BVH (`bvh_header`:
the hierarchy, or a whole file), plus the `joint_map`, `units`, `up` and `handedness` a start
message would carry. The answer is the mapping a session would use (`models.motion.humanoid`:
each body role's joint, the joints left unmapped, units, up axis, the translated joint), or a 422
with the precise kind of problem and every missing role. With `preview=true` the answer is a PNG:
the client's rig (its clip's first frames if the BVH has a MOTION block, else its rig put in the
model's standing pose) above the model skeleton it maps to, drawn Y up in cm.
"""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from models.motion import bvh as bvhio
from models.motion.humanoid import PRESET_NAMES, HumanoidRig, RigError, in_model_world, preset_rig

from . import rig_check
from .api import ApiError, error_responses
from .deps import get_limiter, get_runtime, require_token
from .limits import Principal
from .rig_builds import WorkerFailed
from .runtime import Runtime
from .skeletons import checked_build, rig_from_header

router = APIRouter()
PREVIEW_COST = 10  # requests of the caller's rate a preview costs: it renders (~0.1-1 s of a thread)


class SkeletonCheck(BaseModel):
    model_config = ConfigDict(extra="forbid")

    skeleton: str | None = Field(default=None, description=f"a preset: {', '.join(PRESET_NAMES)}")
    joints: list[str] | None = Field(
        default=None, max_length=1024, description="with `skeleton`: the joints frames carry"
    )
    bvh_header: str | None = Field(default=None, max_length=2_000_000, description="BVH hierarchy, or a whole BVH file")
    joint_map: dict[str, str | None] | None = None
    units: str | None = None
    up: str | None = None
    handedness: str = "right"


class SkeletonReport(BaseModel):
    preset: str | None
    mapping: dict[str, str]
    unmapped: list[str]
    root_joint: str
    up: str
    up_detected: bool
    handedness: str
    units: str | None
    leg_length: float


class RigProblem(BaseModel):
    code: str
    message: str
    missing: list[str] = []


def _rig(body: SkeletonCheck) -> HumanoidRig:
    """The rig, checked as a session's is (`service.rig_check`): limits first, then the match,
    then the retargeter's set-up, so what passes here streams."""
    options = {"joint_map": body.joint_map, "units": body.units, "up": body.up, "handedness": body.handedness}
    if body.bvh_header is not None and body.skeleton is None:
        rig = rig_from_header(body.bvh_header, **options)
    elif body.skeleton is not None and body.bvh_header is None:
        if body.joints is not None:
            rig_check.check_names(body.joints)
        rig = preset_rig(body.skeleton, joints=body.joints, **options)
    else:
        raise RigError("bad_request", "give exactly one of 'skeleton' (a preset) or 'bvh_header'")
    checked_build(rig)
    return rig


def _preview(body: SkeletonCheck, rig: HumanoidRig) -> bytes:
    """Client rig (Y up, cm) above the model skeleton it maps to, as a PNG."""
    import tempfile
    from pathlib import Path

    from models.motion.render import render_contact_sheet
    from models.motion.retarget import default_rig, retarget
    from models.motion.retarget_stream import FrameRetargeter
    from models.motion.skeleton import Motion, from_bvh

    clip = None
    if body.bvh_header is not None and "MOTION" in body.bvh_header:
        try:
            clip = from_bvh(bvhio.parse(body.bvh_header, "bvh"))
        except (bvhio.BvhError, ValueError):
            clip = None
    if clip is not None and clip.num_frames > 1:
        clip = clip.slice(0, min(clip.num_frames, int(clip.fps * 4)))
        model = retarget(clip, fps=clip.fps, source=rig)
    else:  # the rig put in the model's natural standing pose (what the model sees of it)
        fr = FrameRetargeter(rig)
        bn = default_rig()
        sk = rig.skeleton
        rest = np.zeros((1, sk.num_joints, 4))
        rest[..., 3] = 1.0
        hips = np.zeros((1, 3))
        root, rot = fr.to_source(hips, bn.pose[None], rest)
        trans = np.broadcast_to(sk.offsets, (1, sk.num_joints, 3)).copy()
        trans[:, rig.translated] = root
        clip = Motion(sk, rot, trans, 30.0)
        hips_bn, local = fr.to_model(root, rot)
        bn_trans = np.broadcast_to(bn.skeleton.offsets, (1, bn.skeleton.num_joints, 3)).copy()
        bn_trans[:, bn.skeleton.index("Hips")] = hips_bn
        model = Motion(bn.skeleton, local, bn_trans, 30.0)
    frames = 4 if clip.num_frames > 1 else 1
    with tempfile.TemporaryDirectory() as tmp:
        path = render_contact_sheet(
            [in_model_world(clip, rig), model],
            Path(tmp) / "preview.png",
            frames=frames,
            titles=[rig.preset or "client rig", "model skeleton"],
            panel_size=2.2,
        )
        return path.read_bytes()


@router.post(
    "/v1/skeletons",
    response_model=SkeletonReport,
    summary="Check a rig and see how it maps to the model skeleton",
    tags=["skeletons"],
    responses={
        **error_responses(503, notes={503: "`server_busy`: the rig's worker process was lost; try again."}),
        422: {
            "model": RigProblem,
            "description": "The rig cannot be mapped (`code` says why, `missing` lists the body roles "
            "without a joint), or the body does not match its schema (`bad_request`).",
        },
        200: {
            "content": {"image/png": {}},
            "description": "The mapping (JSON), or with `preview=true` a PNG of the mapped rig.",
        },
    },
)
async def check_skeleton(
    request: Request,
    body: SkeletonCheck,
    preview: bool = Query(default=False),
    rt: Runtime = Depends(get_runtime),
    who: Principal = Depends(require_token),
) -> Response:
    """The mapping a session with these rig fields would use, or why it cannot be mapped; a PNG
    preview of the mapped rig with `preview=true` (costs PREVIEW_COST requests of the caller's
    rate). Either runs in a child process within the caller's rig-build gate
    (`service.rig_builds`), never on the event loop; a child lost meanwhile is a 503."""
    if preview:  # the request itself was counted once already
        get_limiter(request).check_request(who, PREVIEW_COST - 1)
    try:
        rig = await rt.rig_builds.run(who.key, _rig, body)
        if preview:
            return Response(await rt.rig_builds.run(who.key, _preview, body, rig), media_type="image/png")
    except RigError as err:
        return JSONResponse({"code": err.code, "message": err.message, "missing": list(err.missing)}, status_code=422)
    except WorkerFailed as err:
        raise ApiError(503, "server_busy", err.message, {"Retry-After": "1"}) from None
    return JSONResponse(rig.report())
