"""The style store behind `/v1/styles`: trained styles of every model plus uploaded ones.

An uploaded clip (BVH with the Bandai Namco or a CMU skeleton, or JSON frames on the Bandai Namco
skeleton) is validated, brought onto the model skeleton at 30 fps, persisted under
`styles_dir/<model>/<name>/` (clip.npz, translator.npz or film.npz, style.json, and job.json, the
record of its fine-tuning job) and turned into a
style: for LPN-FiLM at once (the FiLM generator's embedding of the clip, `add_style_from_clip`),
and with `fine_tune` also a job that fine-tunes a copy of the generator on the clip
(`models.lpn.finetune`) and, if that lowers the loss on the clip's held-back frames, swaps the
style's FiLM vector for the tuned one (`set_style_film`; persisted, so a restart keeps it); for the
LTI model by a fine-tuning job (`models.lti.finetune`). When an LTI job is done the style
is added to the one live model (`add_style`), and a deleted style is removed from it
(`remove_style`), all on the model-step worker thread so no step sees a half-changed model. New
sessions see the change at once; running and resumed sessions carry on unchanged (their state is
brought to the new style set by `upgrade_state` at their next step, `models/interface.py`), and
one whose mix had weight on a deleted style is told so (`style_deleted`) while that share passes
the input through.

Replicas may share one styles folder (a volume mounted by all of them) with `styles_refresh_s` > 0:
each then rescans the folder that often, and at once when a session names a style it does not
know and on every styles or models request, and takes in the styles the others added, fine-tuned
or deleted, so an upload through the
load balancer is usable on every replica and a session resumed on another replica keeps its
uploaded style. A style is written by the replica that received it (its job runs there); the
others only read its folder, and answer `GET /v1/jobs/{id}` for its job from the job.json there.
"""

from __future__ import annotations

import asyncio
import logging
import re
import shutil
import threading
import time
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from .jobs import JobInfo, JobManager
from .settings import ServiceSettings

log = logging.getLogger(__name__)

NAME_RE = re.compile(r"^[a-z0-9](?:[a-z0-9-]{0,38}[a-z0-9])?$")
MODEL_FPS = 30.0
# shared folder: a style still "training" whose style.json changed this recently may be another
# replica's running job, so a starting replica does not mark it interrupted (jobs take < 1 min)
TRAINING_FRESH_S = 600.0


class JobStopped(Exception):
    """A job's work is no longer wanted (its style was deleted, the server is stopping): it stops at
    its next progress report instead of running on."""


class ApiError(Exception):
    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status, self.code, self.message = status, code, message


class ErrorBody(BaseModel):
    code: str
    message: str


class StyleInfo(BaseModel):
    id: str = Field(description="'<model>.<name>'")
    name: str
    model: str
    kind: Literal["trained", "uploaded"]
    status: Literal["ready", "training", "failed"]
    created: float | None = Field(default=None, description="Unix time (trained: weights file time).")
    job_id: str | None = None
    message: str | None = None
    frames: int | None = Field(default=None, description="Uploaded clip length at 30 fps.")
    source: Literal["bvh", "json"] | None = None
    skeleton: str | None = Field(default=None, description="Rig of the uploaded clip (bandai-namco, a preset such as cmu or mixamo, or humanoid).")
    fine_tune: dict | None = Field(default=None, description="Fine-tuning summary: seconds, and for LTI neutral clips and "
                                   "held-out metrics, for LPN-FiLM the loss on the clip's held-back frames before and after.")


class UploadFrames(BaseModel):
    root: list[list[float]] = Field(description="(F, 3) Hips translation, cm")
    rotations: list[list[list[float]]] = Field(description="(F, 22, 4) local rotations, quaternions xyzw, BN joint order")


class StyleUpload(BaseModel):
    name: str
    model: str = "lti"
    frames: UploadFrames
    fps: float = Field(default=30.0, gt=0, le=240)
    fine_tune: bool = False


class UploadAccepted(BaseModel):
    style: StyleInfo
    job: JobInfo | None = None


def style_id(model: str, name: str) -> str:
    return f"{model}.{name}"


# --------------------------------------------------------------------------- clips


def _bn_motion(skeleton, root: np.ndarray, rotations: np.ndarray, fps: float):
    """A Motion on the model skeleton from a Hips track and local rotations (model order)."""
    from models.motion.resample import resample
    from models.motion.skeleton import Motion
    from models.lti.representation import HIPS
    n = len(root)
    trans = np.broadcast_to(skeleton.offsets, (n, skeleton.num_joints, 3)).copy()
    trans[:, HIPS] = root
    motion = Motion(skeleton, rotations / np.linalg.norm(rotations, axis=-1, keepdims=True), trans, float(fps))
    return motion if abs(fps - MODEL_FPS) < 1e-6 else resample(motion, MODEL_FPS)


def _check_finite(*arrays: np.ndarray) -> None:
    if not all(np.all(np.isfinite(a)) for a in arrays):
        raise ApiError(422, "non_finite", "the clip contains NaN or infinite values")


def motion_from_json(upload: StyleUpload, skeleton):
    """JSON frames (BN joint order) -> BN Motion at 30 fps."""
    try:
        root = np.asarray(upload.frames.root, dtype=np.float64)
        rot = np.asarray(upload.frames.rotations, dtype=np.float64)
    except ValueError:
        raise ApiError(422, "bad_frames", "frames must be rectangular arrays: root (F, 3), rotations (F, J, 4)") from None
    j = skeleton.num_joints
    if root.ndim != 2 or root.shape[1] != 3 or rot.ndim != 3 or rot.shape[1:] != (j, 4) or len(root) != len(rot):
        raise ApiError(422, "bad_skeleton" if rot.ndim == 3 and rot.shape[1] != j else "bad_frames",
                       f"expected root (F, 3) and rotations (F, {j}, 4) on the Bandai Namco skeleton "
                       f"(joints {', '.join(skeleton.names)}); got root {root.shape}, rotations {rot.shape}")
    _check_finite(root, rot)
    if np.any(np.linalg.norm(rot, axis=-1) < 1e-6):
        raise ApiError(422, "bad_frames", "a rotation quaternion has (near) zero length")
    return _bn_motion(skeleton, root, rot, upload.fps), "bandai-namco"


def motion_from_bvh(text: str, skeleton):
    """BVH text (BN skeleton or any humanoid rig `models.motion.humanoid` maps) -> BN Motion at
    30 fps, and the source rig (bandai-namco, or the matched preset, or 'humanoid')."""
    from models.motion import bvh as bvhio
    from models.motion.humanoid import RigError, rig_from_bvh
    from models.motion.retarget import retarget
    from models.motion.skeleton import from_bvh
    try:
        motion = from_bvh(bvhio.parse(text, "upload.bvh"))
    except (bvhio.BvhError, ValueError, KeyError, IndexError) as exc:
        raise ApiError(422, "bad_bvh", f"not a readable BVH file: {exc}") from None
    _check_finite(motion.rotations, motion.translations)
    src = motion.skeleton
    if all(n in src.names for n in skeleton.names):
        idx = [src.index(n) for n in skeleton.names]
        hips = src.index("Hips")
        return _bn_motion(skeleton, motion.translations[:, hips], motion.rotations[:, idx], motion.fps), "bandai-namco"
    try:
        rig = rig_from_bvh(text, "upload.bvh")
    except RigError as err:
        raise ApiError(422, "unsupported_skeleton", f"the clip's skeleton is not a humanoid rig I can map: {err.message}") from None
    bn = retarget(motion, fps=MODEL_FPS, source=rig)
    idx = [bn.skeleton.index(n) for n in skeleton.names]
    kind = {"cmu-bvh11": "cmu"}.get(rig.preset, rig.preset) or "humanoid"
    return _bn_motion(skeleton, bn.translations[:, bn.skeleton.index("Hips")], bn.rotations[:, idx], MODEL_FPS), kind


# --------------------------------------------------------------------------- the store


class StyleStore:
    def __init__(self, settings: ServiceSettings, runtime, jobs: JobManager) -> None:
        self.settings, self.rt, self.jobs = settings, runtime, jobs
        self.root = Path(settings.styles_dir)
        self.trained = {name: set(m.styles()) for name, m in runtime.models.items()}
        self.uploaded: dict[str, StyleInfo] = {}  # id -> info
        self.seen: dict[str, float] = {}  # id -> mtime of the style.json last read or written here
        self.shared = settings.styles_refresh_s > 0
        self._refreshing = asyncio.Lock()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.stopping = False

    def bind_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop

    async def stop(self) -> None:
        self.stopping = True  # a running LPN-FiLM fine-tune stops at its next step
        self.jobs.shutdown()

    # ---- persistence -----------------------------------------------------------
    def _dir(self, model: str, name: str) -> Path:
        return self.root / model / name

    def _save_info(self, info: StyleInfo) -> None:
        d = self._dir(info.model, info.name)
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / "style.json.tmp"
        tmp.write_text(info.model_dump_json(indent=1))
        tmp.replace(d / "style.json")
        self.seen[info.id] = (d / "style.json").stat().st_mtime  # our own write: no refresh reads it back

    def _save_job(self, info: StyleInfo, job: JobInfo) -> None:
        """The job's record next to its style (job thread), for replicas sharing the folder and for
        this one after a restart; not if the style was deleted meanwhile (its folder is gone)."""
        d = self._dir(info.model, info.name)
        if self.uploaded.get(info.id) is not info or not d.is_dir():
            return
        tmp = d / f"job.{threading.get_ident()}.tmp"
        try:
            tmp.write_text(job.model_dump_json(indent=1))
            tmp.replace(d / "job.json")
        except FileNotFoundError:  # the style was deleted between the check and the write
            pass

    async def job(self, job_id: str) -> JobInfo | None:
        """A job's record: this replica's own, or else the one stored with the style it produces (a
        job another replica sharing the folder runs or ran, or one from before a restart). A record
        still queued or running that has not changed for TRAINING_FRESH_S lost its replica."""
        job = self.jobs.get(job_id)
        if job is not None:
            return job
        await self.refresh()
        for info in list(self.uploaded.values()):
            path = self._dir(info.model, info.name) / "job.json"
            if info.job_id != job_id or not path.exists():
                continue
            try:
                job, age = JobInfo.model_validate_json(path.read_text()), time.time() - path.stat().st_mtime
            except (OSError, ValueError):
                return None
            if job.status in ("queued", "running") and age > TRAINING_FRESH_S:
                job.status, job.message = "failed", f"interrupted: the replica running it stopped ({job.message})"
            return job
        return None

    def load(self) -> None:
        """The persisted uploaded styles, added to the live models (before any session steps)."""
        if not self.root.is_dir():
            return
        for meta in sorted(self.root.glob("*/*/style.json"), key=lambda p: p.stat().st_mtime):
            info = self._read_info(meta)
            model = None if info is None else self.rt.models.get(info.model)
            if model is None:
                continue
            fresh = time.time() - meta.stat().st_mtime < TRAINING_FRESH_S
            if info.status == "training" and not (self.shared and fresh):
                info.status, info.message = "failed", "interrupted by a server restart; delete and upload again"
                self._save_info(info)
            if info.status == "ready":
                try:
                    self._install(model, info, meta.parent, startup=True)
                except Exception as exc:  # noqa: BLE001
                    log.warning("could not load style %s: %s", info.id, exc)
                    info.status, info.message = "failed", f"could not load its translator: {exc}"
            self.uploaded[info.id] = info
            self.seen.setdefault(info.id, meta.stat().st_mtime)

    @staticmethod
    def _read_info(meta: Path) -> StyleInfo | None:
        try:
            return StyleInfo.model_validate_json(meta.read_text())
        except (OSError, ValueError):
            log.warning("skipping unreadable %s", meta)
            return None

    def _install(self, model, info: StyleInfo, d: Path, startup: bool = False) -> None:
        """A ready style from its folder into `model` (at startup, or by a refresh on the model thread)."""
        if hasattr(model, "add_style_from_clip"):
            self._load_embedded(model, info, d, note_interrupted=startup)
            return
        from models.lti.model import StyleTranslator
        tr = StyleTranslator.load(d / "translator.npz")
        tr.style = info.name
        model.add_style(tr)

    # ---- a styles folder shared with other replicas ---------------------------------
    async def refresh(self) -> None:
        """Take in what other replicas sharing the folder added, changed (an LTI job finished, an
        LPN-FiLM style fine-tuned) or deleted since the last look; nothing unless shared."""
        if not self.shared or self.stopping:
            return
        async with self._refreshing:
            on_disk: dict[str, tuple[Path, float]] = {}
            for meta in self.root.glob("*/*/style.json"):
                try:
                    on_disk[style_id(meta.parent.parent.name, meta.parent.name)] = (meta, meta.stat().st_mtime)
                except OSError:  # deleted between the listing and the stat
                    continue
            for sid, info in list(self.uploaded.items()):
                if sid not in on_disk and not (self._dir(info.model, info.name) / "style.json").exists():
                    await self._forget(info)
            for sid, (meta, mtime) in on_disk.items():
                if self.seen.get(sid) == mtime:
                    continue
                info = self._read_info(meta)
                model = None if info is None else self.rt.models.get(info.model)
                if model is None or info.id != sid:
                    continue
                known = self.uploaded.get(sid)
                newly_ready = info.status == "ready" and (known is None or known.status != "ready")
                refit = hasattr(model, "set_style_film") and (meta.parent / "film.npz").exists()
                if newly_ready or (info.status == "ready" and refit):
                    try:
                        await self.rt.on_model_thread(self._install, model, info, meta.parent)
                    except Exception as exc:  # noqa: BLE001  (half-written by its replica: the next look retries)
                        log.warning("could not take in style %s: %s", sid, exc)
                        continue
                self.uploaded[sid], self.seen[sid] = info, mtime

    async def _forget(self, info: StyleInfo) -> None:
        """Drop an uploaded style whose files are gone (deleted here, or by another replica sharing
        the folder); a job still running on it sees that and stops."""
        if self.uploaded.get(info.id) is not info:
            return
        self.uploaded.pop(info.id, None)
        self.seen.pop(info.id, None)
        model = self.rt.models[info.model]

        def remove() -> None:  # on the worker thread, after any install queued before it
            if info.name in model.styles():
                model.remove_style(info.name)

        await self.rt.on_model_thread(remove)

    async def refresh_loop(self) -> None:
        """Rescan the shared folder every `styles_refresh_s` until the server stops."""
        while not self.stopping:
            await asyncio.sleep(self.settings.styles_refresh_s)
            try:
                await self.refresh()
            except Exception:  # noqa: BLE001  (a bad folder must not end the loop)
                log.exception("styles refresh failed")

    async def ensure_known(self, model_name: str, names) -> None:
        """A session names styles this replica does not have: another may have just added them."""
        model = self.rt.models.get(model_name)
        if model is not None and not set(names) <= set(model.styles()):
            await self.refresh()

    def _load_embedded(self, model, info: StyleInfo, d: Path, note_interrupted: bool = True) -> None:
        """An LPN-FiLM style back from disk: its fine-tuned FiLM vector if a job stored one, else
        the clip embedded again (a fine-tune cut off by the restart is said so in its message)."""
        if (d / "film.npz").exists():
            with np.load(d / "film.npz") as z:
                model.set_style_film(info.name, z["film"])
            return
        clip = np.load(d / "clip.npz")
        model.add_style_from_clip(info.name, _bn_motion(model.skeleton, clip["root"], clip["rotations"], float(clip["fps"])))
        if note_interrupted and info.job_id is not None and info.fine_tune is None and \
                not (self.shared and time.time() - (d / "style.json").stat().st_mtime < TRAINING_FRESH_S):
            info.message = "FiLM parameters from the clip; fine-tuning was interrupted by a server restart"
            self._save_info(info)

    # ---- queries ---------------------------------------------------------------
    def list(self, model: str | None = None) -> list[StyleInfo]:
        out = []
        for name, m in self.rt.models.items():
            if model and name != model:
                continue
            out.extend(self._trained_info(name, m, s) for s in m.styles() if s in self.trained[name])
            out.extend(i for i in self.uploaded.values() if i.model == name)
        return out

    def _trained_info(self, model_name: str, model, style: str) -> StyleInfo:
        created = None
        tr = getattr(model, "translators", {}).get(style)
        src = tr.meta.get("source") if tr is not None and isinstance(tr.meta, dict) else None
        if src and Path(src).exists():
            created = Path(src).stat().st_mtime
        return StyleInfo(id=style_id(model_name, style), name=style, model=model_name, kind="trained",
                         status="ready", created=created)

    def get(self, sid: str) -> StyleInfo:
        for info in self.list():
            if info.id == sid:
                return info
        raise ApiError(404, "unknown_style", f"no style {sid!r} (ids look like 'lti.elderly'; see GET /v1/styles)")

    # ---- changes ---------------------------------------------------------------
    async def delete(self, sid: str) -> None:
        info = self.get(sid)
        if info.kind == "trained":
            raise ApiError(409, "trained_style", f"style {sid!r} is a trained style of model {info.model!r} and "
                           "cannot be deleted; only uploaded styles can")
        shutil.rmtree(self._dir(info.model, info.name), ignore_errors=True)
        await self._forget(info)

    async def upload(self, upload: StyleUpload | None, bvh_text: str | None, name: str, model_name: str,
                     fine_tune: bool) -> UploadAccepted:
        if not NAME_RE.match(name or ""):
            raise ApiError(422, "bad_name", f"style name {name!r} must be a slug: 1-40 characters of a-z, 0-9 and '-', "
                           "starting and ending with a letter or digit")
        model = self.rt.models.get(model_name)
        if model is None:
            raise ApiError(422, "unknown_model", f"unknown model {model_name!r}; available: {', '.join(self.rt.models)}")
        sid = style_id(model_name, name)
        if name in model.styles() or sid in self.uploaded:
            raise ApiError(409, "style_exists", f"model {model_name!r} already has a style named {name!r}")
        embeds = hasattr(model, "add_style_from_clip")  # LPN-FiLM: a clip's FiLM embedding is the style
        if not (embeds or hasattr(model, "add_style")):
            raise ApiError(422, "uploads_unsupported", f"model {model_name!r} cannot take uploaded styles "
                           "(its styles are trained branches); upload to 'lti' with fine_tune=true")
        motion, skel = motion_from_bvh(bvh_text, model.skeleton) if bvh_text is not None else motion_from_json(upload, model.skeleton)
        n, lo, hi = motion.num_frames, self.settings.upload_min_frames, self.settings.upload_max_frames
        if not lo <= n <= hi:
            raise ApiError(422, "bad_length", f"the clip has {n} frames at 30 fps; between {lo} and {hi} are needed")
        if embeds:
            return await self._embed(model_name, name, motion, n, "bvh" if bvh_text is not None else "json", skel,
                                     fine_tune)
        if not fine_tune:
            raise ApiError(422, "fine_tune_required", "an LTI style is a translator identified from the clip: upload "
                           "with fine_tune=true to start the identification job (the clip alone is not a style)")
        from models.lti.finetune import data_available
        if not data_available():
            raise ApiError(409, "training_data_unavailable", "fine-tuning needs the training data (Bandai Namco neutral "
                           "clips), which this server does not have (STYLESTREAM_DATA_DIR)")
        info = StyleInfo(id=sid, name=name, model=model_name, kind="uploaded", status="training", created=time.time(),
                         frames=n, source="bvh" if bvh_text is not None else "json", skeleton=skel)
        d = self._dir(model_name, name)
        d.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(d / "clip.npz", root=motion.translations[:, 1], rotations=motion.rotations, fps=MODEL_FPS)
        self.uploaded[sid] = info
        ref = next(iter(model.translators.values())).ref
        job = self.jobs.submit("fine_tune", lambda progress: self._fine_tune_job(info, motion, ref, progress),
                               target=sid, on_failure=lambda msg: self._job_failed(sid, msg),
                               record=lambda job: self._save_job(info, job))
        info.job_id = job.id
        self._save_info(info)
        return UploadAccepted(style=info.model_copy(), job=job)

    async def _embed(self, model_name: str, name: str, motion, frames: int, source: str, skel: str,
                     fine_tune: bool) -> UploadAccepted:
        """A clip-embedding model (LPN-FiLM): the FiLM generator turns the clip into a style that
        sessions can use as soon as this returns; no training data is involved. With `fine_tune`
        a job also fine-tunes the generator on the clip and then swaps in the tuned FiLM vector."""
        from models.lpn.finetune import min_frames
        if fine_tune and frames < min_frames():
            raise ApiError(422, "bad_length", f"the clip has {frames} frames at 30 fps; fine-tuning needs at least "
                           f"{min_frames()} (a fifth of it is held back to check the result); upload it without fine_tune")
        model = self.rt.models[model_name]
        try:
            await self.rt.on_model_thread(model.add_style_from_clip, name, motion)
        except ValueError as exc:
            raise ApiError(422, "bad_clip", str(exc)) from None
        sid = style_id(model_name, name)
        info = StyleInfo(id=sid, name=name, model=model_name, kind="uploaded", status="ready", created=time.time(),
                         frames=frames, source=source, skeleton=skel, message="FiLM parameters from the clip")
        d = self._dir(model_name, name)
        d.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(d / "clip.npz", root=motion.translations[:, 1], rotations=motion.rotations, fps=MODEL_FPS)
        self.uploaded[sid] = info
        if not fine_tune:
            self._save_info(info)
            return UploadAccepted(style=info.model_copy())
        job = self.jobs.submit("fine_tune", lambda progress: self._film_job(info, motion, progress), target=sid,
                               on_failure=lambda msg: self._film_job_failed(info, msg),
                               record=lambda job: self._save_job(info, job))
        info.job_id, info.message = job.id, "FiLM parameters from the clip; fine-tuning the FiLM generator"
        self._save_info(info)
        return UploadAccepted(style=info.model_copy(), job=job)

    # ---- the LPN-FiLM job (job thread) ---------------------------------------------
    def _film_job(self, info: StyleInfo, motion, progress) -> dict:
        from models.lpn.finetune import FineTuneConfig, fine_tune

        def report(fraction: float, loss: float) -> None:
            if self.uploaded.get(info.id) is not info:  # deleted (maybe uploaded again): stop spending the CPU
                raise JobStopped(f"style {info.id!r} was deleted while its FiLM generator was being fine-tuned")
            if self.stopping:
                raise JobStopped("the server is stopping")
            progress(0.02 + 0.93 * fraction, f"fine-tuning the FiLM generator: loss {loss:.4f}")

        progress(0.0, "building the clip's training samples")
        model = self.rt.models[info.model]
        res = fine_tune(model.generator(), motion, FineTuneConfig(steps=self.settings.lpn_fine_tune_steps), report)
        summary = res.summary()
        progress(0.97, "installing the fine-tuned FiLM vector" if res.improved else "keeping the clip's embedding")
        fut = asyncio.run_coroutine_threadsafe(self._install_film(info, res.film if res.improved else None, summary),
                                               self.loop)
        summary["installed"] = fut.result(timeout=60)
        return summary

    async def _install_film(self, info: StyleInfo, film: np.ndarray | None, summary: dict) -> bool:
        """Swap the style's FiLM vector for the fine-tuned one (None: fine-tuning did not lower the
        held-back loss, the clip embedding stays) and persist it; nothing if the style was deleted."""
        if self.uploaded.get(info.id) is not info:
            return False
        model = self.rt.models[info.model]
        if film is not None:
            def swap() -> None:  # on the worker thread; a removal queued before it wins
                if info.name in model.styles():
                    model.set_style_film(info.name, film)

            await self.rt.on_model_thread(swap)
            if self.uploaded.get(info.id) is not info:  # deleted meanwhile: its removal runs after the swap
                return False
            d = self._dir(info.model, info.name)
            np.savez(d / "film.tmp.npz", film=film)
            (d / "film.tmp.npz").replace(d / "film.npz")
        info.fine_tune = {**summary, "installed": film is not None}
        info.message = ("fine-tuned FiLM generator" if film is not None else
                        "FiLM parameters from the clip (fine-tuning did not lower the loss on the clip's held-back frames)")
        self._save_info(info)
        return film is not None

    def _film_job_failed(self, info: StyleInfo, message: str) -> None:
        """Job thread: the style keeps its clip embedding and says (on the event loop, where deletes
        run) why it is not fine-tuned. A stopping server leaves that to the restart (`load`)."""
        if self.stopping:
            return

        def note() -> None:
            if self.uploaded.get(info.id) is info:
                info.message = f"FiLM parameters from the clip; fine-tuning failed: {message}"
                self._save_info(info)

        self.loop.call_soon_threadsafe(note)

    # ---- the LTI job (job thread) ------------------------------------------------
    def _fine_tune_job(self, info: StyleInfo, motion, ref, progress) -> dict:
        from models.lti.finetune import fine_tune
        res = fine_tune(motion, info.name, ref, progress)
        d = self._dir(info.model, info.name)
        if info.id in self.uploaded:
            res.translator.save(d / "translator.npz")
        summary = {"seconds": round(res.seconds, 2), "neutral_clips": res.neutral_clips, "train_frames": res.train_frames,
                   "state_dim": int(res.translator.n), "heldout": res.heldout}
        progress(0.97, "installing the style")
        asyncio.run_coroutine_threadsafe(self._activate(info.id, res.translator, summary), self.loop).result(timeout=60)
        return summary

    async def _activate(self, sid: str, tr, summary: dict) -> None:
        info = self.uploaded.get(sid)
        if info is None:  # deleted while training
            return
        await self.rt.on_model_thread(self.rt.models[info.model].add_style, tr)
        if self.uploaded.get(sid) is not info:  # deleted meanwhile: its removal was queued after the add
            return
        info.status, info.message, info.fine_tune = "ready", "fine-tuned", summary
        self._save_info(info)

    def _job_failed(self, sid: str, message: str) -> None:
        info = self.uploaded.get(sid)
        if info is not None:
            info.status, info.message = "failed", message
            self._save_info(info)
