"""LPN-FiLM's uploaded styles (`models.interface.ClipStyles`), mixed into `LPNModel`: a clip
gives a FiLM vector at once (the generator's embedding); a fine-tuning job may replace it and
saves it as `film.npz`. A copy of the model shares the weights and owns its style table.
"""

from __future__ import annotations

import copy
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Self

import numpy as np

from models.interface import ClipStyles, FineTuned, Progress, StyleRejected
from models.motion.skeleton import Motion

if TYPE_CHECKING:
    from .network import LPN

FILM_FILE = "film.npz"


class LPNStyles(ClipStyles[np.ndarray]):
    """What `LPNModel` adds to take uploaded styles; it relies on the model's `set_style_film`,
    `generator` and its style lock."""

    clip_style_note = "FiLM parameters from the clip"
    tuning_note = "fine-tuning the FiLM generator"
    _lock: threading.Lock
    if TYPE_CHECKING:

        def set_style_film(self, name: str, film: np.ndarray) -> None: ...
        def generator(self) -> LPN: ...

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

    def fine_tune_style(self, name: str, clip: Motion, progress: Progress, steps: int) -> FineTuned[np.ndarray]:
        """The FiLM vector of a copy of the generator fine-tuned on `clip` for `steps` Adam steps;
        None (the clip's embedding stays) unless it lowered the loss on the held-back frames."""
        from .finetune import FineTuneConfig, fine_tune

        def report(fraction: float, loss: float) -> None:
            progress(0.02 + 0.93 * fraction, f"fine-tuning the FiLM generator: loss {loss:.4f}")

        progress(0.0, "building the clip's training samples")
        res = fine_tune(self.generator(), clip, FineTuneConfig(steps=steps), report)
        progress(0.97, "installing the fine-tuned FiLM vector" if res.improved else "keeping the clip's embedding")
        if res.improved:
            return FineTuned(res.film, res.summary(), "fine-tuned FiLM generator")
        return FineTuned(
            None,
            res.summary(),
            "FiLM parameters from the clip (fine-tuning did not lower the loss on the clip's held-back frames)",
        )

    def install_style(self, name: str, style: np.ndarray) -> None:
        self.set_style_film(name, style)

    def save_style(self, style: np.ndarray, folder: Path) -> None:
        np.savez(folder / "film.tmp.npz", film=style)
        (folder / "film.tmp.npz").replace(folder / FILM_FILE)

    def has_saved_style(self, folder: Path) -> bool:
        return (folder / FILM_FILE).exists()

    def load_style(self, name: str, folder: Path) -> np.ndarray:
        with np.load(folder / FILM_FILE) as z:
            return z["film"]
