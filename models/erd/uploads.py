"""Style-ERD's uploaded styles (`models.interface.ClipStyles`), mixed into `runtime.ERDModel`.

A trained style is a residual LSTM branch, a one-hot decoder code and its stages; an upload is
the same without retraining: at once a zero branch (the neutral reconstruction) and an output
prior from the clip (`upload_stages`); after the job (`finetune.py`) the nearest style's branch
fitted to the clip. A model without uploads computes exactly what it did; installing replaces
the stacked arrays, never changes them in place.
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Self

import numpy as np
from numpy.typing import DTypeLike

from ..data.archives import is_available
from ..interface import ClipStyles, FineTuned, Progress, StyleRejected
from ..motion.bn_skeleton import HIPS
from ..motion.skeleton import Motion, Skeleton
from ..motion.style_carry import StyleCarry
from ..stages import Pipeline
from .dataset import DATASET, TARGET_STYLES
from .features import FeatureMaker
from .slow_carry import GAITS, SlowPrior, by_gait
from .stages import stacked
from .twist_range import TwistRange
from .upload_stages import SOURCES_FILE, Sources, clip_rotations, fit_stages, nearest_style

STYLE_FILE = "erd_style.npz"
MIN_FRAMES = 60  # 2 s: the stages' statistics need a few steps of the clip


@dataclass
class Upload:
    """An uploaded style: branch (PyTorch LSTM names), initial state, decoder code (6,), stages."""

    name: str
    nearest: str  # the trained style its branch and code started from ("": none, the zero branch)
    lstm: dict[str, np.ndarray]
    h0: np.ndarray
    c0: np.ndarray
    code: np.ndarray
    stages: dict[str, SlowPrior | TwistRange] = field(default_factory=dict)

    def save(self, path: Path) -> None:
        arrays = {f"lstm.{k}": v for k, v in self.lstm.items()}
        arrays |= {"h0": self.h0, "c0": self.c0, "code": self.code, "nearest": np.array(self.nearest)}
        for key, stage in self.stages.items():
            if isinstance(stage, SlowPrior):
                for name, carry in ((key, stage.carry), *((g + key, stage.gait(g)) for g in GAITS)):
                    if carry is not None:
                        arrays |= carry.named(f"{name}.")
                if stage.fast is not None:
                    arrays[f"{key}.fast"] = stage.fast
            else:
                arrays |= {"twist.mean": stage.mean, "twist.lo": stage.lo, "twist.hi": stage.hi}
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **arrays)  # type: ignore[arg-type]
        tmp.replace(path)

    @classmethod
    def load(cls, name: str, path: Path, twist_joints: TwistRange | None) -> Upload:
        with np.load(path) as z:
            a = {k: z[k] for k in z.files}

        def carry(key: str, gait: str = "") -> StyleCarry | None:
            """The carry saved under `key`, or its `gait`'s (a prefix of `GAITS`)."""
            return StyleCarry.read(a, f"{gait}{key}.") if f"{gait}{key}.source" in a else None

        stages: dict[str, Any] = {}
        for key, hips in (("leaf_prior", -1), ("output_prior", HIPS)):
            if (walk := carry(key)) is not None:
                fast = a.get(f"{key}.fast")
                stages[key] = SlowPrior((name,), walk, hips=hips, fast=fast, **by_gait(partial(carry, key)))
        if twist_joints is not None and "twist.mean" in a:
            stages["twist_range"] = TwistRange(
                twist_joints.joints, twist_joints.axes, a["twist.mean"], a["twist.lo"], a["twist.hi"], (name,)
            )
        lstm = {k[5:]: v for k, v in a.items() if k.startswith("lstm.")}
        return cls(name, str(a["nearest"]), lstm, a["h0"], a["c0"], a["code"], stages)


class BuiltIn(NamedTuple):
    """The trained styles' stacked LSTM weights and stages, which uploads are appended to."""

    lstm_w: list[np.ndarray]
    lstm_b: list[np.ndarray]
    stages: Pipeline


def branch_weights(params: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    """One LSTM branch's parameters under their PyTorch names (`weight_ih_l0`, ...)."""
    return {k[len(prefix) :]: v for k, v in params.items() if k.startswith(prefix)}


def neutral_branch(model: Any, stages: dict[str, SlowPrior | TwistRange]) -> Upload:
    """A style with zero branch weights, state and code: the network's neutral reconstruction."""
    lstm = {k: np.zeros(v.shape, np.float32) for k, v in branch_weights(model.p, "branches.0.").items()}
    h0, c0 = (np.zeros(model.p[k][0].shape, np.float32) for k in ("style_h0", "style_c0"))
    return Upload("", "", lstm, h0, c0, np.zeros(len(TARGET_STYLES)), stages)


def runtime_layout(lstm: dict[str, np.ndarray], layers: int, H: int, dtype: DTypeLike) -> tuple[list, list]:
    """A branch's LSTM as the step multiplies it (`ERDModel._prepare_weights`)."""
    scale = np.ones(4 * H)
    scale[2 * H : 3 * H] = 2.0  # gates i, f, g, o (PyTorch order): g is the tanh one
    w, b = [], []
    for layer in range(layers):  # PyTorch's names, sorted: bias_hh, bias_ih, weight_hh, weight_ih
        b_hh, b_ih, w_hh, w_ih = (lstm[k] for k in sorted(lstm) if k.split("_")[-1][1:] == str(layer))
        w.append((np.concatenate([w_ih.T, w_hh.T]) * scale).astype(dtype))
        b.append(((b_ih + b_hh) * scale)[None].astype(dtype))
    return w, b


class ERDStyles(ClipStyles[Upload]):
    """What `ERDModel` adds to take uploaded styles."""

    clip_style_note = "the network's neutral reconstruction, an output prior fitted from the clip"
    tuning_note = "fitting the style's residual branch"
    _lock: threading.Lock
    uploads: tuple[Upload, ...]
    built_in: BuiltIn
    weights_dir: Path | None
    if TYPE_CHECKING:
        p: dict[str, np.ndarray]
        maker: FeatureMaker
        fps: float
        Ln: int
        H: int
        dtype: np.dtype
        skeleton: Skeleton
        stages: Pipeline
        lstm_w: list[np.ndarray]
        lstm_b: list[np.ndarray]
        branches: tuple[str, ...]
        codes: np.ndarray | None

    def with_own_styles(self) -> Self:
        twin = copy.copy(self)
        twin._lock = threading.Lock()
        twin._scratch = threading.local()  # type: ignore[attr-defined]
        return twin

    @property
    def sources(self) -> Sources:
        """The trained styles' fit sources (`upload_stages.py`), read once."""
        held = getattr(self, "_sources", None)
        if held is None:
            path = None if self.weights_dir is None else self.weights_dir / SOURCES_FILE
            if path is None or not path.exists():
                raise StyleRejected(
                    "uploads_unavailable",
                    f"this server's Style-ERD weights lack {SOURCES_FILE} "
                    "(`python -m models.erd fit --stages upload_sources`)",
                    unavailable=True,
                )
            held = self._sources = Sources.load(path)
        return held

    def check_upload(self, frames: int, fine_tune: bool) -> None:
        if frames < MIN_FRAMES:
            raise StyleRejected("bad_length", f"the clip has {frames} frames at 30 fps; Style-ERD needs {MIN_FRAMES}")
        self.sources  # noqa: B018  (raises where the server lacks them)
        if fine_tune:
            if not is_available(DATASET):
                raise StyleRejected(
                    "training_data_unavailable",
                    "fine-tuning a Style-ERD style pairs the clip with dataset 2's neutral clips, which this "
                    "server does not have (STYLESTREAM_DATA_DIR); upload without fine_tune",
                    unavailable=True,
                )

    def style_from_clip(self, clip: Motion, name: str = "") -> Upload:
        """The neutral reconstruction with an output prior carried to `clip`."""
        q, x = clip_rotations(self, self._checked(clip))
        stages = fit_stages(self.built_in.stages, self.skeleton, q, self.sources.nearest(x))
        return replace(neutral_branch(self, stages), name=name)

    def nearest_branch(self, clip: Motion, name: str = "") -> Upload:
        """The nearest trained style's branch and code (the job's start), with the instant stages."""
        instant = self.style_from_clip(clip, name)
        q, _ = clip_rotations(self, clip)
        leaf = self.built_in.stages.leaf_prior
        s = nearest_style(leaf.carry.mean, q) if isinstance(leaf, SlowPrior) else 0
        lstm = {k: v.astype(np.float32) for k, v in branch_weights(self.p, f"branches.{s}.").items()}
        h0, c0 = (self.p[k][s].astype(np.float32) for k in ("style_h0", "style_c0"))
        return replace(instant, nearest=TARGET_STYLES[s], lstm=lstm, h0=h0, c0=c0, code=np.eye(len(TARGET_STYLES))[s])

    def _checked(self, clip: Motion) -> Motion:
        if clip.skeleton.names != self.skeleton.names:
            raise ValueError("a style clip must be on the model skeleton (Bandai Namco, 22 joints)")
        if clip.num_frames < MIN_FRAMES:
            raise ValueError(f"style clip too short: {clip.num_frames} frames, need at least {MIN_FRAMES}")
        return clip

    def fine_tune_style(self, name: str, clip: Motion, progress: Progress, steps: int) -> FineTuned[Upload]:
        from .finetune import fine_tune

        progress(0.0, "fitting the clip's stages")
        start = self.nearest_branch(clip, name)
        tuned, summary = fine_tune(self, start, clip, progress)
        if tuned is None:
            return FineTuned(None, summary, f"{self.clip_style_note} (fitting a branch did not bring it closer)")
        return FineTuned(tuned, summary, "a residual branch fitted from the clip, stages fitted from the clip")

    def network_only(self, name: str, style: Upload) -> Self:
        """A copy with `style` as `name` and no priors or twist range: what an upload's prior carries from."""
        twin = self.with_own_styles()
        bare = twin.built_in.stages.replace(leaf_prior=None, output_prior=None, twist_range=None)
        twin.built_in = twin.built_in._replace(stages=bare)
        twin.install_style(name, replace(style, stages={}))
        return twin

    def install_style(self, name: str, style: Upload) -> None:
        with self._lock:
            if name in TARGET_STYLES:
                raise ValueError(f"{name!r} is a trained Style-ERD style")
            kept = [u for u in self.uploads if u.name != name]
            self._use(tuple(kept) + (replace(style, name=name),))

    def remove_style(self, name: str) -> None:
        with self._lock:
            if name not in [u.name for u in self.uploads]:
                raise KeyError(f"unknown uploaded style {name!r}")
            self._use(tuple(u for u in self.uploads if u.name != name))

    def save_style(self, style: Upload, folder: Path) -> None:
        style.save(folder / STYLE_FILE)

    def has_saved_style(self, folder: Path) -> bool:
        return (folder / STYLE_FILE).exists()

    def load_style(self, name: str, folder: Path) -> Upload:
        twists = self.built_in.stages.twist_range
        return Upload.load(name, folder / STYLE_FILE, twists if isinstance(twists, TwistRange) else None)

    def _use(self, uploads: tuple[Upload, ...]) -> None:
        """Replace the stacked branches, codes and stages by the trained styles' and `uploads`'."""
        dt, base = self.dtype, self.built_in
        self.lstm_w, self.lstm_b = list(base.lstm_w), list(base.lstm_b)
        for u in uploads:
            w, b = runtime_layout(u.lstm, self.Ln, self.H, dt)
            self.lstm_w = [np.concatenate([a, x[None]]) for a, x in zip(self.lstm_w, w)]
            self.lstm_b = [np.concatenate([a, x[None]]) for a, x in zip(self.lstm_b, b)]
        n = len(TARGET_STYLES)
        self.codes = np.concatenate([np.eye(n), *(u.code[None] for u in uploads)]).astype(dt) if uploads else None
        self.uploads = uploads
        self.branches = self.branches[:1] + tuple(TARGET_STYLES) + tuple(u.name for u in uploads)
        self.stages = stacked(base.stages, [(u.name, u.stages) for u in uploads])
