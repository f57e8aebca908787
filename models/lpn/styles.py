"""LPN-FiLM's uploaded styles (`models.interface.ClipStyles`), mixed into `LPNModel`: a clip gives a
FiLM vector at once (the generator's embedding); a fine-tuning job may replace it (`film.npz`).

Each upload also gets an output prior fitted from its clip as a built-in style's is from its TRAIN
clips. The network reads its input only as control, so the prior's source is the network's output
for the clip's own trajectory (its content and pace); it depends on the FiLM vector, so it is
streamed when the style is made, not stored.
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Self

import numpy as np

from models.interface import ClipStyles, FineTuned, Progress, StyleRejected
from models.motion.skeleton import Motion, Skeleton
from models.motion.style_carry import StyleCarry
from models.stages import Pipeline

if TYPE_CHECKING:
    from .network import LPN

FILM_FILE = "film.npz"
MAKING = "upload being made"  # the style name a twin streams the clip toward to fit its prior
PRIOR_MIN_FRAMES = 60  # a clip shorter than this (after the network's first second) gets no prior


@dataclass(frozen=True)
class LPNUpload:
    """An uploaded style: FiLM vector (4, H) and output prior (one-style carry; None: none)."""

    film: np.ndarray
    prior: StyleCarry | None = None


class LPNStyles(ClipStyles[LPNUpload]):
    """What `LPNModel` adds to take uploaded styles."""

    clip_style_note = "FiLM parameters and output prior from the clip"
    tuning_note = "fine-tuning the FiLM generator"
    _lock: threading.Lock
    skeleton: Skeleton
    stages: Pipeline
    if TYPE_CHECKING:

        def set_style_film(self, name: str, film: np.ndarray) -> None: ...
        def set_style_upload(self, name: str, film: np.ndarray, prior: StyleCarry | None) -> None: ...
        def film_from_clip(self, motion: Motion) -> np.ndarray: ...
        def generator(self) -> LPN: ...

    def style_from_clip(self, clip: Motion) -> LPNUpload:
        """The clip's FiLM vector (`film_from_clip`) and the output prior fitted for it (`upload_prior`)."""
        film = self.film_from_clip(clip)
        return LPNUpload(film, self.upload_prior(clip, film))

    def upload_prior(self, clip: Motion, film: np.ndarray) -> StyleCarry | None:
        """The output prior for `film` from its clip, the network's output for its trajectory as source."""
        from .carriage import SKIP_FRAMES, made
        from .output_prior import CARRIED, FIT_FRAMES, SOURCE_FLOOR_DEG

        if self.stages.output_prior is None or clip.num_frames < SKIP_FRAMES + PRIOR_MIN_FRAMES:
            return None
        twin = self.with_own_styles()
        twin.stages = twin.stages.without("output_prior", "arm_coupling")  # as the built-in fit runs it
        twin.set_style_film(MAKING, film)
        source = made(twin, MAKING, [clip.slice(0, FIT_FRAMES)])[0].astype(np.float64)  # type: ignore[arg-type]
        fixed = tuple(j for j, n in enumerate(self.skeleton.names) if n not in CARRIED)
        target = clip.rotations.astype(np.float64)
        return StyleCarry.fit([source], [target], fixed, source_floor=np.radians(SOURCE_FLOOR_DEG))

    def with_own_styles(self) -> Self:
        twin = copy.copy(self)
        twin._lock = threading.Lock()
        return twin

    def check_upload(self, frames: int, fine_tune: bool) -> None:
        from .finetune import min_frames  # torch training code, loaded when a style is uploaded

        if fine_tune and frames < min_frames():
            raise StyleRejected(
                "bad_length",
                f"the clip has {frames} frames at 30 fps; fine-tuning needs at least "
                f"{min_frames()} (a fifth of it is held back to check the result); upload it without "
                "fine_tune",
            )

    def fine_tune_style(self, name: str, clip: Motion, progress: Progress, steps: int) -> FineTuned[LPNUpload]:
        """A generator tuned on `clip`, its prior refitted; None unless the held-back loss fell."""
        from .finetune import FineTuneConfig, fine_tune

        def report(fraction: float, loss: float) -> None:
            progress(0.02 + 0.93 * fraction, f"fine-tuning the FiLM generator: loss {loss:.4f}")

        progress(0.0, "building the clip's training samples")
        res = fine_tune(self.generator(), clip, FineTuneConfig(steps=steps), report)
        if res.improved:
            progress(0.96, "fitting the output prior for the fine-tuned FiLM vector")
            tuned = LPNUpload(res.film, self.upload_prior(clip, res.film))
            progress(0.99, "installing the fine-tuned FiLM vector")
            return FineTuned(tuned, res.summary(), "fine-tuned FiLM generator")
        progress(0.97, "keeping the clip's embedding")
        return FineTuned(
            None,
            res.summary(),
            "FiLM parameters from the clip (fine-tuning did not lower the loss on the clip's held-back frames)",
        )

    def install_style(self, name: str, style: LPNUpload) -> None:
        self.set_style_upload(name, style.film, style.prior)

    def save_style(self, style: LPNUpload, folder: Path) -> None:
        arrays: dict[str, Any] = {"film": style.film}
        if style.prior is not None:
            arrays |= style.prior.named("prior_")  # a saved upload's prior, if any
        np.savez(folder / "film.tmp.npz", **arrays)
        (folder / "film.tmp.npz").replace(folder / FILM_FILE)

    def has_saved_style(self, folder: Path) -> bool:
        return (folder / FILM_FILE).exists()

    def load_style(self, name: str, folder: Path) -> LPNUpload:
        with np.load(folder / FILM_FILE) as z:
            prior = StyleCarry.read(z, "prior_") if "prior_source" in z else None
            return LPNUpload(z["film"], prior)
