"""The style store behind `/v1/styles`: trained styles of every model plus uploaded ones, their
files, their fine-tuning jobs, and the styles folder shared with other replicas.

A model takes uploaded styles only if it declares so (`models.interface.UploadedStyles`); the
store knows nothing else of the methods. An uploaded clip (already on the model skeleton at
30 fps, `clips.py`) is persisted under `styles_dir/<model>/<name>/` (clip.npz, the method's
own saved parameters, style.json, and job.json, the record of its fine-tuning job) and turned
into a style:

- a `ClipStyles` model (LPN-FiLM, Style-ERD) makes one from the clip at once (`style_from_clip`, on a worker
  thread beside the model's steps; only `install_style` runs between them); with
  `fine_tune` a job also fine-tunes (`fine_tune_style`) and, if that gives better parameters,
  swaps them in (`install_style`) and saves them, so a restart keeps them;
- any other uploading model (LTI) gets its style from the fine-tuning job alone, added when
  the job is done.

Every change to a live model (add, replace, remove) runs on the model-step worker thread, so no
step sees a half-changed model. New sessions see the change at once; running and resumed
sessions carry on unchanged (their state is brought to the new style set by `upgrade_state` at
their next step, `models/interface.py`), and one whose mix had weight on a deleted style is told
so (`style_deleted`) while that share passes the input through.

Replicas may share one styles folder (a volume mounted by all of them) with `styles_refresh_s` > 0:
each then rescans the folder that often, and at once when a session names a style it does not
know and on every styles or models request, and takes in the styles the others added, fine-tuned
or deleted, so an upload through the load balancer is usable on every replica and a session
resumed on another replica keeps its uploaded style. A style is written by the replica that
received it (its job runs there); the others only read its folder, and answer
`GET /v1/jobs/{id}` for its job from the job.json there.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import shutil
import threading
import time
import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from models.interface import ClipStyles, FineTuned, Progress, StreamingModel, StyleRejected, UploadedStyles
from models.motion.skeleton import Motion

from .api import ApiError, StyleInfo, UploadAccepted
from .background import in_background, save_npz
from .batcher import ModelThread
from .clip_worker import Body, ClipBudget, ClipDecoder, Kind, Upload
from .clips import MODEL_FPS, clip_on_skeleton, hips_track
from .jobs import JobInfo, JobManager
from .limits import Principal
from .settings import ServiceSettings

log = logging.getLogger(__name__)

NAME_RE = re.compile(r"^[a-z0-9](?:[a-z0-9-]{0,38}[a-z0-9])?$")
# shared folder: a style still "training" whose style.json changed this recently may be another
# replica's running job, so a starting replica does not mark it interrupted (jobs take < 1 min)
TRAINING_FRESH_S = 600.0
INCOMING = ".incoming"  # styles_dir/.incoming/<random>: an upload's files until they are complete


class JobStopped(Exception):
    """A job's work is no longer wanted (its style was deleted, the server is stopping): it stops at
    its next progress report instead of running on."""


def style_id(model: str, name: str) -> str:
    return f"{model}.{name}"


def visible(info: StyleInfo, who: Principal | None) -> bool:
    """An uploaded style is its tenant's (and an admin's); one uploaded without tokens is everyone's."""
    return who is None or who.admin or not info.owner or info.owner == who.tenant


class StyleStore:
    def __init__(
        self, settings: ServiceSettings, models: dict[str, StreamingModel], model_thread: ModelThread, jobs: JobManager
    ) -> None:
        """`models` are the server's own (`own_style_set`): the store adds and removes styles on
        them, on `model_thread`, the thread their steps run on."""
        self.settings, self.models, self.model_thread, self.jobs = settings, models, model_thread, jobs
        self.root = Path(settings.styles_dir)
        self.trained = {name: set(m.styles()) for name, m in models.items()}
        self.uploaded: dict[str, StyleInfo] = {}  # id -> info
        self.seen: dict[str, float] = {}  # id -> mtime of the style.json last read or written here
        self.shared = settings.styles_refresh_s > 0
        self._claimed: set[str] = set()  # ids of uploads under way (`upload`)
        self.decoder = ClipDecoder(
            ClipBudget(
                settings.upload_min_frames,
                settings.upload_max_frames,
                settings.upload_min_fps,
                settings.upload_max_fps,
                settings.upload_decode_cpu_s,
                settings.upload_decode_memory_mb,
                settings.upload_decode_wall_s,
            ),
            settings.upload_decoders,
        )
        self._refreshing = asyncio.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self.stopping = False

    def bind_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop the store's state belongs to (job threads hand their results to it)."""
        if self._loop is None:
            raise RuntimeError("StyleStore.bind_loop was not called")
        return self._loop

    async def stop(self) -> None:
        self.stopping = True  # a running fine-tune stops at its next progress report
        self.jobs.shutdown()
        await in_background(self.decoder.close)

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

    @staticmethod
    def _saved_clip(model: StreamingModel, d: Path) -> Motion:
        with np.load(d / "clip.npz") as clip:
            return clip_on_skeleton(model.skeleton, clip["root"], clip["rotations"], float(clip["fps"]))

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
        for left in self.root.glob(f"{INCOMING}/*"):  # an upload cut off by a crash (not one under way elsewhere)
            with contextlib.suppress(OSError):
                if time.time() - left.stat().st_mtime > TRAINING_FRESH_S:
                    shutil.rmtree(left, ignore_errors=True)
        for meta in sorted(self.root.glob("*/*/style.json"), key=lambda p: p.stat().st_mtime):
            info = self._read_info(meta)
            model = None if info is None else self.models.get(info.model)
            if info is None or not isinstance(model, UploadedStyles):
                continue
            fresh = time.time() - meta.stat().st_mtime < TRAINING_FRESH_S
            if info.status == "training" and not (self.shared and fresh):
                info.status, info.message = "failed", "interrupted by a server restart; delete and upload again"
                self._save_info(info)
            if info.status == "ready":
                try:
                    self._install(model, info, meta.parent)
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

    def _saved_style(self, model: UploadedStyles[Any], info: StyleInfo, d: Path) -> Any:
        """The parameters of a ready style in its folder: those saved there, or for a clip style
        without any, made from its clip again. Leaves the model as it is (any thread)."""
        if isinstance(model, ClipStyles) and not model.has_saved_style(d):
            return model.style_from_clip(self._saved_clip(model, d))
        return model.load_style(info.name, d)

    def _install(self, model: UploadedStyles[Any], info: StyleInfo, d: Path) -> None:
        """A ready style from its folder into `model` at startup (a clip style's fine-tune cut
        off by a restart is said so in its message)."""
        model.install_style(info.name, self._saved_style(model, info, d))
        if (
            isinstance(model, ClipStyles)
            and not model.has_saved_style(d)
            and info.job_id is not None
            and info.fine_tune is None
            and not (self.shared and time.time() - (d / "style.json").stat().st_mtime < TRAINING_FRESH_S)
        ):
            info.message = f"{model.clip_style_note}; fine-tuning was interrupted by a server restart"
            self._save_info(info)

    # ---- a styles folder shared with other replicas ---------------------------------
    async def refresh(self) -> None:
        """Take in what other replicas sharing the folder added, changed (a job finished, a clip
        style fine-tuned) or deleted since the last look; nothing unless shared."""
        if not self.shared or self.stopping:
            return
        async with self._refreshing:
            on_disk: dict[str, tuple[Path, float]] = {}
            for meta in self.root.glob("*/*/style.json"):
                try:
                    on_disk[style_id(meta.parent.parent.name, meta.parent.name)] = (meta, meta.stat().st_mtime)
                except OSError:  # deleted between the listing and the stat
                    continue
            for sid, known in list(self.uploaded.items()):
                if sid not in on_disk and not (self._dir(known.model, known.name) / "style.json").exists():
                    await self._forget(known)
            for sid, (meta, mtime) in on_disk.items():
                if self.seen.get(sid) == mtime:
                    continue
                info = self._read_info(meta)
                model = None if info is None else self.models.get(info.model)
                if info is None or not isinstance(model, UploadedStyles) or info.id != sid:
                    continue
                before = self.uploaded.get(sid)
                newly_ready = info.status == "ready" and (before is None or before.status != "ready")
                refit = isinstance(model, ClipStyles) and model.has_saved_style(meta.parent)  # fine-tuned since
                if newly_ready or (info.status == "ready" and refit):
                    try:  # made beside the model's steps, installed between them
                        style = await in_background(self._saved_style, model, info, meta.parent)
                        await self.model_thread.run(model.install_style, info.name, style)
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
        model = self.models[info.model]
        if not isinstance(model, UploadedStyles):
            return

        def remove() -> None:  # on the worker thread, after any install queued before it
            if info.name in model.styles():
                model.remove_style(info.name)

        await self.model_thread.run(remove)

    async def refresh_loop(self) -> None:
        """Rescan the shared folder every `styles_refresh_s` until the server stops."""
        while not self.stopping:
            await asyncio.sleep(self.settings.styles_refresh_s)
            try:
                await self.refresh()
            except Exception:  # noqa: BLE001  (a bad folder must not end the loop)
                log.exception("styles refresh failed")

    async def ensure_known(self, model_name: str, names: Iterable[str]) -> None:
        """A session names styles this replica does not have: another may have just added them."""
        model = self.models.get(model_name)
        if model is not None and not set(names) <= set(model.styles()):
            await self.refresh()

    # ---- queries ---------------------------------------------------------------
    def list(self, model: str | None = None, who: Principal | None = None) -> list[StyleInfo]:
        """Trained styles and the uploaded ones `who` may see (None: all, for the server itself)."""
        out: list[StyleInfo] = []
        for name, m in self.models.items():
            if model and name != model:
                continue
            out.extend(self._trained_info(name, m, s) for s in m.styles() if s in self.trained[name])
            out.extend(i for i in self.uploaded.values() if i.model == name and visible(i, who))
        return out

    def hidden_from(self, who: Principal, model_name: str) -> set[str]:
        """Names of `model_name`'s uploaded styles that belong to other tenants: to `who`, as if
        they did not exist (not listed, not usable in a session, 404)."""
        return {i.name for i in self.uploaded.values() if i.model == model_name and not visible(i, who)}

    @staticmethod
    def _trained_info(model_name: str, model: StreamingModel, style: str) -> StyleInfo:
        source = model.style_file(style) if isinstance(model, UploadedStyles) else None
        created = source.stat().st_mtime if source is not None and source.exists() else None
        return StyleInfo(
            id=style_id(model_name, style),
            name=style,
            model=model_name,
            kind="trained",
            status="ready",
            created=created,
        )

    def get(self, sid: str, who: Principal | None = None) -> StyleInfo:
        for info in self.list(who=who):
            if info.id == sid:
                return info
        raise ApiError(404, "unknown_style", f"no style {sid!r} (ids look like 'lti.elderly'; see GET /v1/styles)")

    # ---- changes ---------------------------------------------------------------
    async def delete(self, sid: str, who: Principal) -> None:
        info = self.get(sid, who)
        if info.kind == "trained":
            raise ApiError(
                409,
                "trained_style",
                f"style {sid!r} is a trained style of model {info.model!r} and "
                "cannot be deleted; only uploaded styles can",
            )
        self._claimed.add(info.id)  # the name stays taken until its files are gone
        try:
            await self._forget(info)  # first: a fine-tune job on it stops recording into its folder
            await self._remove_files(info.model, info.name)
        finally:
            self._claimed.discard(info.id)

    def _upload_target(self, name: str, model_name: str) -> UploadedStyles[Any]:
        """The model an upload of style `name` goes to, or the ApiError why there is none."""
        if not NAME_RE.match(name or ""):
            raise ApiError(
                422,
                "bad_name",
                f"style name {name!r} must be a slug: 1-40 characters of a-z, 0-9 and '-', "
                "starting and ending with a letter or digit",
            )
        model = self.models.get(model_name)
        if model is None:
            raise ApiError(422, "unknown_model", f"unknown model {model_name!r}; available: {', '.join(self.models)}")
        sid = style_id(model_name, name)
        if name in model.styles() or sid in self.uploaded or sid in self._claimed:
            raise ApiError(409, "style_exists", f"model {model_name!r} already has a style named {name!r}")
        if not isinstance(model, UploadedStyles):
            raise ApiError(
                422,
                "uploads_unsupported",
                f"model {model_name!r} cannot take uploaded styles "
                "(its styles are trained branches); upload to 'lti' with fine_tune=true",
            )
        return model

    async def upload(
        self, kind: Upload, body: Body, fields: dict[str, Any], who: Principal, content_type: str = ""
    ) -> UploadAccepted:
        """A new style from an uploaded clip: `body` is the BVH file or the JSON upload (as the
        chunks it was read in), `fields`
        the name, model and fine_tune given beside it (form fields, query). A bad name or model
        is refused before the clip is decoded; the decoding (`clip_worker`) brings it onto the
        model's skeleton at 30 fps in a child process. The name is claimed before anything is
        awaited, so of concurrent uploads of one name exactly one gets it (the others 409), and
        the style's files are written before it goes live, so a failed write leaves no trace."""
        if "name" in fields:
            self._upload_target(fields["name"], fields.get("model") or "lti")
        skeletons = {name: m.skeleton for name, m in self.models.items() if isinstance(m, UploadedStyles)}
        clip = await self.decoder.decode(kind, body, fields, skeletons, content_type)
        name, model_name = clip.fields.get("name") or "", clip.fields.get("model") or "lti"
        fine_tune = bool(clip.fields.get("fine_tune"))
        model = self._upload_target(name, model_name)
        sid = style_id(model_name, name)
        self._claimed.add(sid)
        try:
            assert clip.motion is not None  # decoded for every model that takes uploads
            return await self._create(sid, model, clip.motion, clip.rig, clip.source, fine_tune, who.tenant)
        finally:
            self._claimed.discard(sid)

    async def _create(
        self,
        sid: str,
        model: UploadedStyles[Any],
        motion: Motion,
        rig: str,
        source: Kind,
        fine_tune: bool,
        owner: str,
    ) -> UploadAccepted:
        model_name, name = sid.split(".", 1)
        try:
            model.check_upload(motion.num_frames, fine_tune)
        except StyleRejected as err:
            raise ApiError(409 if err.unavailable else 422, err.code, err.message) from None
        info = StyleInfo(
            id=sid,
            name=name,
            model=model_name,
            kind="uploaded",
            status="training",
            created=time.time(),
            frames=motion.num_frames,
            source=source,
            skeleton=rig,
            owner=owner,
        )
        await self._write_new(info, motion)
        if isinstance(model, ClipStyles):  # the style exists as soon as this returns; a job may improve it
            try:  # made beside the model's steps (the FiLM generator over the clip), installed between them
                style = await in_background(model.style_from_clip, motion)
                await self.model_thread.run(model.install_style, name, style)
            except ValueError as exc:
                await self._remove_files(model_name, name)
                raise ApiError(422, "bad_clip", str(exc)) from None
            info.status, info.message = "ready", model.clip_style_note
        self.uploaded[sid] = info  # before its job starts: a job whose style is not there stops
        job = None
        if fine_tune:
            job = self.jobs.submit(
                "fine_tune",
                lambda progress: self._fine_tune_job(info, model, motion, progress),
                target=sid,
                on_failure=lambda message: self._job_failed(info, model, message),
                record=lambda job: self._save_job(info, job),
            )
            info.job_id = job.id
            if isinstance(model, ClipStyles):
                info.message = f"{model.clip_style_note}; {model.tuning_note}"
        try:
            self._save_info(info)
        except OSError as exc:  # live already (a clip style): take it back, as if never uploaded
            await self._forget(info)
            await self._remove_files(model_name, name)
            raise ApiError(507, "storage_full", f"the style could not be stored: {exc.strerror or exc}") from None
        return UploadAccepted(style=info.model_copy(), job=job)

    async def _remove_files(self, model: str, name: str) -> None:
        """A style's folder removed off the event loop: unlinking its files took milliseconds on
        the loop, which showed as the healthy sessions' slowest round trips after each DELETE."""
        await in_background(shutil.rmtree, self._dir(model, name), ignore_errors=True)

    async def _write_new(self, info: StyleInfo, motion: Motion) -> None:
        """The clip and a first style.json into the style's folder, written under a temporary
        name and renamed into place, off the event loop; 507 (and nothing left) if the disk
        refuses."""
        final = self._dir(info.model, info.name)
        tmp = self.root / INCOMING / uuid.uuid4().hex  # no model is named so: no scan takes it for a style

        def write() -> None:
            try:
                tmp.mkdir(parents=True)
                final.parent.mkdir(parents=True, exist_ok=True)
                save_npz(tmp / "clip.npz", root=hips_track(motion), rotations=motion.rotations, fps=MODEL_FPS)
                (tmp / "style.json").write_text(info.model_dump_json(indent=1))
                shutil.rmtree(final, ignore_errors=True)  # leftovers of a style deleted on another replica
                tmp.rename(final)
            except OSError:
                shutil.rmtree(tmp, ignore_errors=True)
                raise

        try:
            await in_background(write)
        except OSError as exc:
            raise ApiError(507, "storage_full", f"the style could not be stored: {exc.strerror or exc}") from None
        self.seen[info.id] = (final / "style.json").stat().st_mtime

    # ---- fine-tuning jobs (job thread) ------------------------------------------------
    def _fine_tune_job(
        self, info: StyleInfo, model: UploadedStyles[Any], motion: Motion, progress: Progress
    ) -> dict[str, Any]:
        def report(fraction: float, message: str) -> None:
            if self.uploaded.get(info.id) is not info:  # deleted (maybe uploaded again): stop spending the CPU
                raise JobStopped(f"style {info.id!r} was deleted while it was being fine-tuned")
            if self.stopping:
                raise JobStopped("the server is stopping")
            progress(fraction, message)

        # the steps setting is named for LPN-FiLM, the one method whose fine-tune iterates; LTI's ignores it
        tuned = model.fine_tune_style(info.name, motion, report, self.settings.lpn_fine_tune_steps)
        installed = asyncio.run_coroutine_threadsafe(self._install_tuned(info, model, tuned), self.loop).result(
            timeout=60
        )
        if isinstance(model, ClipStyles):  # the job refined a style that exists: say whether it changed
            return {**tuned.summary, "installed": installed}
        return tuned.summary

    async def _install_tuned(self, info: StyleInfo, model: UploadedStyles[Any], tuned: FineTuned[Any]) -> bool:
        """Add (or swap in) the job's style and save it; nothing if the style was deleted. A job
        that found nothing better (`tuned.style` None) leaves the clip's style as it is."""
        if self.uploaded.get(info.id) is not info:
            return False
        if tuned.style is not None:

            def install() -> None:  # on the worker thread; a removal queued before it wins
                if self.uploaded.get(info.id) is info:
                    model.install_style(info.name, tuned.style)

            await self.model_thread.run(install)
            if self.uploaded.get(info.id) is not info:  # deleted meanwhile: its removal runs after the install
                return False
            model.save_style(tuned.style, self._dir(info.model, info.name))
        installed = tuned.style is not None
        info.status, info.message = "ready", tuned.message
        info.fine_tune = {**tuned.summary, "installed": installed} if isinstance(model, ClipStyles) else tuned.summary
        self._save_info(info)
        return installed

    def _job_failed(self, info: StyleInfo, model: UploadedStyles[Any], message: str) -> None:
        """Job thread. A clip style stays as the clip made it and says (on the event loop, where
        deletes run) why it is not fine-tuned; any other style failed. A stopping server leaves
        that to the restart (`load`)."""
        if self.stopping:
            return
        if not isinstance(model, ClipStyles):
            if self.uploaded.get(info.id) is info:
                info.status, info.message = "failed", message
                self._save_info(info)
            return

        def note() -> None:
            if self.uploaded.get(info.id) is info:
                info.message = f"{model.clip_style_note}; fine-tuning failed: {message}"
                self._save_info(info)

        self.loop.call_soon_threadsafe(note)
