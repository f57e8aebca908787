"""The browser viewer (`GET /viewer`, its static files under `/viewer/static/`) and the demo clip
it streams (`GET /v1/demo/clip`).

The clip also carries the oriented solids (head with nose, hands with thumb, feet) of the Bandai
Namco and CMU rigs, calibrated by `models.motion.orientation` on the committed reference poses, so
the page draws head, hand and foot rotations exactly as the matplotlib renders do.

The demo clip is a 4-second neutral Bandai Namco walk committed as JSON next to the viewer
(`clients/viewer/demo_walk.json`, ~100 KB, CC BY-NC 4.0 like the dataset), so serving it needs
no mocap data. If that file is missing, the clip is cut from the mocap data when `models.data`
can give it, and otherwise made by rocking the committed one-frame pose. Regenerate the file with

    .venv/bin/python -m service.viewer
"""

from __future__ import annotations

import asyncio
import json
import logging
from functools import lru_cache
from pathlib import Path

import numpy as np
from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel

from models.motion.assets import bandai_namco_pose, cmu_pose
from models.motion.orientation import rig, solids_json
from models.motion.rotations import euler_to_quat, quat_mul

log = logging.getLogger(__name__)

VIEWER_DIR = Path(__file__).resolve().parent.parent / "clients" / "viewer"
DEMO_FILE = VIEWER_DIR / "demo_walk.json"
DEMO_SOURCE = "bandai-namco-2/dataset-2_walk_normal_021 (validation split)"
STATIC_TYPES = {
    ".js": "text/javascript",
    ".css": "text/css",
    ".html": "text/html",
    ".json": "application/json",
    ".svg": "image/svg+xml",
    ".png": "image/png",
}


class DemoFrames(BaseModel):
    root: list[list[float]]  # (F, 3) Hips translation, cm, Y up
    rotations: list[list[list[float]]]  # (F, J, 4) local quaternions xyzw


class ViewerSolid(BaseModel):
    part: str  # head, nose, hand_l, thumb_l, foot_l, toe_l, ...
    joint: int  # index into the rig's `joints`
    rotation: list[float]  # xyzw: the part's frame in the joint's local frame
    corners: list[list[float]]  # (8, 3) in the part's frame; corner k at (bit 2, bit 1, bit 0) of k
    side: int  # 1 left, -1 right, 0 centre
    mark: bool  # nose and thumb stubs


class ViewerRig(BaseModel):
    name: str
    joints: list[str]
    solids: list[ViewerSolid]


class DemoClip(BaseModel):
    name: str
    source: str
    licence: str
    joints: list[str]
    parents: list[int]
    offsets: list[list[float]]  # (J, 3) rest translation in the parent's frame, cm
    root_joint: int  # the joint whose translation `frames.root` is (Hips)
    fps: float
    frames: DemoFrames
    rigs: list[ViewerRig] = []  # oriented solids per known skeleton (`demo_clip` adds them)


def _skeleton_fields() -> dict:
    sk = bandai_namco_pose().skeleton
    return {
        "joints": list(sk.names),
        "parents": [int(p) for p in sk.parents],
        "offsets": np.round(sk.offsets, 4).tolist(),
        "root_joint": sk.index("Hips"),
    }


def _frames(root: np.ndarray, rotations: np.ndarray) -> dict:
    rotations = rotations / np.linalg.norm(rotations, axis=-1, keepdims=True)
    rotations = np.where(rotations[..., 3:] < 0, -rotations, rotations)  # w >= 0, the short way round
    return {"root": np.round(root, 3).tolist(), "rotations": np.round(rotations, 5).tolist()}


def walk_from_data(seconds: float = 4.0) -> dict:
    """A loopable `seconds`-long stretch of a neutral validation-split walk: the start frame and
    length are chosen so the last frame's pose is closest to the first's (one gait cycle fits)."""
    from models.data import build_index, load_motion, select

    clip = select(build_index(), dataset="bandai-namco-2", style="normal", content="walk", split="val")[0]
    motion = load_motion(clip)
    hips = motion.skeleton.index("Hips")
    rot = motion.rotations / np.linalg.norm(motion.rotations, axis=-1, keepdims=True)
    n = int(round(seconds * motion.fps))
    best: tuple[float, int, int] | None = None
    for start in range(10, max(11, motion.num_frames - n - 20)):
        for length in range(n - 15, n + 16):
            if start + length >= motion.num_frames:
                continue
            # pose distance (all joints but the root) between the first frame and the one after the last
            d = 1.0 - np.abs(np.sum(rot[start, 2:] * rot[start + length, 2:], axis=-1))
            cost = float(d.sum())
            if best is None or cost < best[0]:
                best = (cost, start, length)
    if best is None:
        raise ValueError(f"{clip.name}: too short for a {seconds:g} s loop")
    _, start, length = best
    root = motion.translations[start : start + length, hips].copy()
    return {
        "name": "walk (neutral)",
        "source": f"{clip.dataset}/{clip.name}, frames {start}-{start + length - 1}",
        "licence": "CC BY-NC 4.0, Bandai Namco Research Motion Dataset (Bandai Namco Studios Inc.)",
        **_skeleton_fields(),
        "fps": float(motion.fps),
        "frames": _frames(root, motion.rotations[start : start + length]),
    }


def rocking_pose(seconds: float = 4.0, fps: float = 30.0) -> dict:
    """No mocap data: the committed standing pose, swaying side to side with swinging arms."""
    pose = bandai_namco_pose()
    sk = pose.skeleton
    t = np.arange(int(seconds * fps)) / fps
    phase = 2 * np.pi * t / 2.0  # one sway every 2 s: loops cleanly over 4 s
    rotations = np.repeat(pose.rotations[:1], len(t), axis=0)
    hips = sk.index("Hips")
    root = np.repeat(pose.translations[:1, hips], len(t), axis=0)
    root[:, 0] += 4.0 * np.sin(phase)
    root[:, 1] += 1.0 * np.cos(2 * phase)

    def turn(joint: str, axis: str, degrees: np.ndarray) -> None:
        j = sk.index(joint)
        order = axis + "".join(a for a in "XYZ" if a != axis)
        q = euler_to_quat(np.stack([degrees, 0 * degrees, 0 * degrees], -1), order)
        rotations[:, j] = quat_mul(rotations[:, j], q)

    turn("Hips", "Z", 4.0 * np.sin(phase))
    turn("Spine", "Z", -3.0 * np.sin(phase))
    for side, sign in (("L", 1.0), ("R", -1.0)):
        turn(f"UpperArm_{side}", "Y", 12.0 * sign * np.sin(phase))
        turn(f"LowerArm_{side}", "Y", 8.0 * sign * (1 + np.sin(phase)) / 2)
    return {
        "name": "standing sway (generated: no mocap data)",
        "source": "models/motion/assets/bandai_namco.bvh, rocked",
        "licence": "CC BY-NC 4.0, Bandai Namco Research Motion Dataset (Bandai Namco Studios Inc.)",
        **_skeleton_fields(),
        "fps": fps,
        "frames": _frames(root, rotations),
    }


def viewer_rigs() -> list[dict]:
    """The head / hand / foot solids of the Bandai Namco and CMU rigs, for the page to pose by joint rotations."""
    return [
        {"name": name, "joints": list(pose.skeleton.names), "solids": solids_json(rig(pose))}
        for name, pose in (("bandai_namco", bandai_namco_pose()), ("cmu", cmu_pose()))
    ]


@lru_cache(maxsize=1)
def demo_clip() -> dict:
    return {**_demo_motion(), "rigs": viewer_rigs()}


def _demo_motion() -> dict:
    if DEMO_FILE.exists():
        try:
            return DemoClip.model_validate_json(DEMO_FILE.read_bytes()).model_dump(exclude={"rigs"})
        except ValueError as exc:
            log.warning("%s is not a valid demo clip (%s); falling back", DEMO_FILE, str(exc)[:200])
    try:
        return walk_from_data()
    except Exception as exc:  # noqa: BLE001 - no data, no archives, ...: any failure means "use the pose"
        log.info("no mocap data for the demo clip (%s); serving a rocked standing pose", exc)
        return rocking_pose()


def build_router() -> APIRouter:
    router = APIRouter()

    @router.get("/viewer", include_in_schema=False)
    async def viewer_page() -> FileResponse:
        return FileResponse(VIEWER_DIR / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})

    @router.get("/viewer/static/{name:path}", include_in_schema=False)
    async def viewer_static(name: str) -> FileResponse:
        """The viewer's files and its vendored libraries (vendor/three/): ES modules need a
        JavaScript MIME type; nothing outside clients/viewer/ and no other file types are served."""
        path = (VIEWER_DIR / name).resolve()
        if not path.is_relative_to(VIEWER_DIR) or path.suffix not in STATIC_TYPES or not path.is_file():
            raise HTTPException(404, "not found")
        return FileResponse(path, media_type=STATIC_TYPES[path.suffix], headers={"Cache-Control": "no-cache"})

    @router.get("/viewer/hold", include_in_schema=False)
    async def viewer_hold(ms: int = 20) -> Response:
        """Answers after `ms` (at most 1000) real milliseconds. With `?autoplay=1` the page keeps one
        of these pending until its stream has started: a headless browser running on virtual time
        (`--virtual-time-budget`) does not advance it while a fetch is pending, so the page gets the
        real time it needs to connect and receive frames before the screenshot."""
        await asyncio.sleep(max(0, min(ms, 1000)) / 1000)
        return Response(status_code=204, headers={"Cache-Control": "no-store"})

    @router.get("/v1/demo/clip", response_model=DemoClip, tags=["viewer"])
    async def get_demo_clip() -> JSONResponse:
        """A short clip for the viewer and for trying the protocol: the Bandai Namco skeleton
        (joints, parents, offsets in cm, Y up) and frames (`root`: Hips translation; `rotations`:
        local quaternions xyzw, in `joints` order) at `fps`, and `rigs`: per known skeleton, the
        head / hand / foot solids to pose by the joints' world rotations."""
        return JSONResponse(demo_clip())

    return router


router = build_router()


if __name__ == "__main__":
    clip = walk_from_data()
    DEMO_FILE.write_text(json.dumps(clip, separators=(",", ":")) + "\n")
    print(
        f"{DEMO_FILE}: {len(clip['frames']['root'])} frames at {clip['fps']:g} fps from {clip['source']}, "
        f"{DEMO_FILE.stat().st_size / 1024:.0f} KB"
    )
