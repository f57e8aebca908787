"""The stages after Style-ERD's network (`models.stages`), in step order; the model card says what
each does (`python -m models.erd fit`). The leaf prior carries the input's rotations before the
decoding reads them; the others change the decoded rotations. Uploads stack their own (`stacked`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from ..motion import hinge_floor
from ..motion.bn_skeleton import HIPS
from ..stages import Pipeline, Stage, StageSpec
from . import twist_range
from .rotation_prior import LEAF_FILE, OUTPUT_FILE, fit_leaf, fit_output
from .slow_carry import SlowPrior
from .twist_range import TWIST_FILE, TwistRange

STAGES = (
    StageSpec("leaf_prior", LEAF_FILE, lambda path, _: SlowPrior.load(path), fit_leaf),
    StageSpec("output_prior", OUTPUT_FILE, lambda path, _: SlowPrior.load(path, HIPS), fit_output),
    hinge_floor.STAGE,  # before the twist range: it turns bones about themselves only
    StageSpec("twist_range", TWIST_FILE, lambda path, _: TwistRange.load(path), twist_range.fit),
)
ON_INPUT = "leaf_prior"  # the last stage that carries the input (the decoding reads its output)


def stacked(stages: Pipeline, uploads: Sequence[tuple[str, Mapping[str, Stage]]]) -> Pipeline:
    """The trained styles' stages with each upload's as one more style."""
    out: dict[str, Any] = {}
    for key, stage in stages.stages:
        if isinstance(stage, (SlowPrior, TwistRange)):
            out[key] = stage.stacked([(name, own[key]) for name, own in uploads if key in own])  # type: ignore[misc]
    return stages.replace(**out)
