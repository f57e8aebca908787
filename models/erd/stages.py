"""The fitted stages after Style-ERD's network, as one record: what `runtime.load` reads beside
the weights, what the stream's step and the whole-clip path (`offline.py`) run frame by frame,
and what an upload fits (`upload_stages.py`) and stacks onto the trained styles'. A stage left
None is off."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..motion.bn_skeleton import HIPS
from ..motion.hinge import HINGE_FILE, Hinges
from ..motion.hinge_floor import HingeFloor
from ..motion.skeleton import Skeleton
from ..motion.style_carry import StyleCarry
from ..motion.twist import transfer_twist
from .rotation_prior import PRIOR_FILES
from .slow_carry import carry_slow
from .twist_range import TWIST_FILE, TwistRange

if TYPE_CHECKING:
    from .uploads import Upload


@dataclass(frozen=True)
class ErdStages:
    """In the order the step runs them (the model card's table says what each does and how it is
    fitted)."""

    leaf_prior: StyleCarry | None = None  # the input's twists and leaves carried to the style (`rotation_prior.py`)
    run_leaf_prior: StyleCarry | None = None  # the same fitted on runs, for frames the input runs in (`gait.py`)
    hinges: Hinges | None = None  # elbows and knees decoded as hinges (`models.motion.hinge`; None: the input's twists)
    output_prior: StyleCarry | None = None  # the network's rotations carried to the style's real ones
    run_output_prior: StyleCarry | None = None
    hinge_floor: HingeFloor | None = None  # elbows and knees held at their least real bend
    twist_range: TwistRange | None = None  # the arms' twists kept in the style's real interval (`twist_range.py`)
    # the decoding's twists and leaves without a leaf prior: the network's own (a network trained
    # on them, `train.py --network_twists`) or the input's (one trained on positions only)
    network_twists: bool = False

    @classmethod
    def load(cls, folder: Path, skeleton: Skeleton, core_only: bool = False, hinges: bool = True) -> ErdStages:
        """The stages fitted beside the weights in `folder`; `core_only`: only the hinges, which
        are part of the decoding; `hinges=False`: without them (for comparison)."""
        hinge_file = folder / HINGE_FILE
        decode = Hinges.load(hinge_file) if hinges and hinge_file.exists() else None
        config = folder / "config.json"
        own = config.exists() and json.loads(config.read_text()).get("train_config", {}).get("network_twists", False)
        if core_only:
            return cls(hinges=decode, network_twists=own)
        priors = {key: StyleCarry.load(folder / name) for key, name in PRIOR_FILES.items() if (folder / name).exists()}
        twists = TwistRange.load(folder / TWIST_FILE) if (folder / TWIST_FILE).exists() else None
        floor = HingeFloor.load(skeleton, folder)
        return cls(hinges=decode, hinge_floor=floor, twist_range=twists, network_twists=own, **priors)

    def without(self, *names: str) -> ErdStages:
        """These stages off, the rest as they are."""
        off: dict[str, Any] = dict.fromkeys(names)
        return replace(self, **off)

    def stacked(self, uploads: tuple[Upload, ...]) -> ErdStages:
        """The trained styles' stages with each upload's appended as one more style (a stage the
        trained styles lack stays off)."""
        if not uploads:
            return self
        carries: dict[str, Any] = {
            key: StyleCarry.stack([carry, *(getattr(u.stages, key) for u in uploads)])
            for key in PRIOR_FILES
            if (carry := getattr(self, key)) is not None
        }
        twists = self.twist_range
        if twists is not None:
            ups = [u.stages.twist_range for u in uploads]
            twists = TwistRange(
                twists.joints,
                twists.axes,
                np.concatenate([twists.mean, *(t.mean for t in ups)]),  # type: ignore[union-attr]
                np.concatenate([twists.lo, *(t.lo for t in ups)]),  # type: ignore[union-attr]
                np.concatenate([twists.hi, *(t.hi for t in ups)]),  # type: ignore[union-attr]
            )
        return replace(self, twist_range=twists, **carries)

    def __call__(
        self,
        skeleton: Skeleton,
        rot_in: np.ndarray,
        decoded: np.ndarray,
        slow_in: np.ndarray,
        slow_out: np.ndarray,
        weights: np.ndarray,
        share: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame of B sessions: the input's rotations `rot_in` and the network's decoded ones
        (B, J, 4), the slow copies before the frame, the style weights (B, S) and run shares (B,)
        -> the output rotations and the new slow copies (`slow_carry.py`)."""
        source, slow_in = carry_slow(self.leaf_prior, self.run_leaf_prior, rot_in, slow_in, weights, share)
        if self.network_twists and self.leaf_prior is None:
            source = decoded
        out = transfer_twist(skeleton, source, decoded, hinges=self.hinges)
        out, slow_out = carry_slow(self.output_prior, self.run_output_prior, out, slow_out, weights, share, hips=HIPS)
        if self.hinge_floor is not None:  # before the twist range: it turns bones about themselves only
            out = self.hinge_floor(out)
        if self.twist_range is not None:
            out = self.twist_range(out, weights)
        return out, slow_in, slow_out
