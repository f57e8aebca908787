"""The LTI model's uploaded styles (`models.interface.UploadedStyles`), mixed into `LTIStyleModel`.

A style is a `StyleTranslator`, so a clip becomes one only by identification: a fine-tuning job
(`finetune.py`) pairing it with neutral training clips this server must have. It is saved as
`translator.npz`; `add_style` / `remove_style` replace, never mutate, so copies stay apart.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import TYPE_CHECKING, Self

from models.data.archives import is_available
from models.interface import FineTuned, Progress, StyleRejected, UploadedStyles
from models.motion.skeleton import Motion

if TYPE_CHECKING:
    from .model import StyleTranslator

TRANSLATOR_FILE = "translator.npz"


class LTIStyles(UploadedStyles["StyleTranslator"]):
    """What `LTIStyleModel` adds to take uploaded styles."""

    translators: dict[str, StyleTranslator]
    if TYPE_CHECKING:

        def add_style(self, tr: StyleTranslator) -> None: ...

    def with_own_styles(self) -> Self:
        return copy.copy(self)

    def check_upload(self, frames: int, fine_tune: bool) -> None:
        if not fine_tune:
            raise StyleRejected(
                "fine_tune_required",
                "an LTI style is a translator identified from the clip: upload "
                "with fine_tune=true to start the identification job (the clip alone is not a style)",
            )
        if not is_available("bandai-namco-2"):
            raise StyleRejected(
                "training_data_unavailable",
                "fine-tuning needs the training data (Bandai Namco neutral "
                "clips), which this server does not have (STYLESTREAM_DATA_DIR)",
                unavailable=True,
            )

    def fine_tune_style(self, name: str, clip: Motion, progress: Progress, steps: int) -> FineTuned[StyleTranslator]:
        """Identify a translator for `clip` (`steps` does not apply: identification is closed-form)."""
        from .finetune import fine_tune
        from .raised_arm import fit_upload

        ref = next(iter(self.translators.values())).ref  # the reference rotations every translator shares
        res = fine_tune(clip, name, ref, progress)
        progress(0.96, "fitting the raised arm")  # as for a built-in style, from the style's clip
        res.translator.raised_arm = fit_upload(res.translator, clip, ref)
        summary = {
            "seconds": round(res.seconds, 2),
            "neutral_clips": res.neutral_clips,
            "train_frames": res.train_frames,
            "state_dim": int(res.translator.n),
            "heldout": res.heldout,
            "raised_arm": res.translator.raised_arm is not None,
        }
        progress(0.97, "installing the style")
        return FineTuned(res.translator, summary, "fine-tuned")

    def install_style(self, name: str, style: StyleTranslator) -> None:
        style.style = name
        self.add_style(style)

    def save_style(self, style: StyleTranslator, folder: Path) -> None:
        style.save(folder / TRANSLATOR_FILE)

    def has_saved_style(self, folder: Path) -> bool:
        return (folder / TRANSLATOR_FILE).exists()

    def load_style(self, name: str, folder: Path) -> StyleTranslator:
        from .model import StyleTranslator  # model.py mixes this class in, so it cannot be imported at the top

        tr = StyleTranslator.load(folder / TRANSLATOR_FILE)
        tr.style = name
        return tr

    def style_file(self, name: str) -> Path | None:
        tr = self.translators.get(name)
        source = tr.meta.get("source") if tr is not None and isinstance(tr.meta, dict) else None
        return Path(source) if source else None
