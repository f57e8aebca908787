"""LPN-FiLM's arm coupling: a style's forearms moved with its upper arms, shoulders and chest as
in its real clips (`python -m models.lpn fit --stages arm_coupling` writes `ARM_COUPLING_FILE`).
The output prior maps joints one by one, so it cannot put a forearm in step with an arm swing
(`models.motion.coupling`, fitted per gait).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..eval.run import DATASET, INPUT_STYLE
from ..motion.coupling import Coupling, Link
from .carriage import fitted_styles, locomotion, made

if TYPE_CHECKING:
    from .runtime import LPNModel

ARM_COUPLING_FILE = "arm_coupling.npz"
LINKS: tuple[Link, ...] = tuple((f"LowerArm_{s}", (f"UpperArm_{s}", f"Shoulder_{s}", "Chest")) for s in "LR")
FIT_FRAMES = 300


def fit(model: LPNModel, styles: list[str] | None = None, dataset: str = DATASET) -> Coupling:
    """The coupling of `styles` (default: all with TRAIN clips), walks and runs apart."""
    styles = styles or fitted_styles(model.styles(), dataset)
    clips = locomotion(dataset)
    model = model.with_own_styles()
    model.stages = model.stages.without("arm_coupling")

    def real(style: str, gait: str) -> list[np.ndarray]:
        return [m.rotations for m in clips(style)[gait]]

    def output(style: str, gait: str) -> list[np.ndarray]:
        return made(model, style, [m.slice(0, FIT_FRAMES) for m in clips(INPUT_STYLE)[gait]])

    return Coupling.fit(styles, LINKS, model.skeleton.names, real, output)
