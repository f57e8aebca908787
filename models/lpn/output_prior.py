"""LPN-FiLM's output prior: the upper body's rotations carried from what the network makes toward
a style to that style's real rotations (`OUTPUT_PRIOR_FILE` beside the weights, written by
`python -m models.lpn.output_prior [STYLE ...]`; `runtime.LPNModel` applies it).

The arm carriage (`carriage.py`) moves each joint's mean; what the rotation judge also reads is
how the arms and spine swing about it. Driven by the validation locomotion inputs, LPN-FiLM's
active walks had the real style's mean arm pose after the carriage but not its pumping swing, and
were read as masculine by the rotation judge (13 of 13 walks and turns). Style-ERD's output prior
(`models/motion/style_carry.py`) maps each joint's deviations from the network's mean with the
linear optimal-transport map between the network's and the real style's Gaussians of them, then
clamps into the style's real p98 radius: a typical frame of the network lands as a typical frame
of the style, with the style's spread in each direction. Here it is fitted on the spine, neck,
head and arms (`carriage.UPPER_BODY`; the legs are the foot planter's), from the network with its
carriage in place, driven by the `normal` TRAIN locomotion clips, to the style's real TRAIN
locomotion; applied after the carriage and before the rotation balls. Only the styles whose
validation judges gained and lost nothing get one (the model card's table): fitted for every
style, youthful's content fell by a clip.

Active carries its legs as well (`CARRIED`): its walks were read as exhausted by the position
judge (7 of 13 validation locomotion inputs right, 10 of 13 with the legs); exhausted, already
read right, lost a clip of content in running sessions with them, and keeps the upper body only.
The foot planter runs after the prior, so planted feet stay planted.

The network hardly moves some joints along some axis (a neck twist, an elbow's side bend): taken
at face value, the map stretched those to the style's spread with gains up to 621 (active Neck),
magnifying the network's arithmetic noise (its products run in bfloat16 on some CPUs). The fit
takes the network's spread as at least `SOURCE_FLOOR_DEG` along every axis (gains 4.1 at most).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..motion.feet import LEG_JOINTS
from ..motion.style_carry import StyleCarry
from .carriage import LOCOMOTION, SKIP_FRAMES, UPPER_BODY, train_clips

OUTPUT_PRIOR_FILE = "output_prior.npz"
CARRIED = {"active": UPPER_BODY + LEG_JOINTS, "exhausted": UPPER_BODY}  # per style, chosen on validation (module doc)
SOURCE_FLOOR_DEG = 2.0  # the network's least spread along any axis, as the fit takes it (module doc)
PRIOR_ROWS = ("prior_source", "prior_mean", "prior_map", "prior_radius", "prior_on")  # its style-table rows
FIT_FRAMES = 300


@dataclass(frozen=True)
class OutputPrior:
    """Per fitted style: `carry`'s rows (source mean, style mean, map, clamp radius per joint)."""

    styles: tuple[str, ...]
    carry: StyleCarry

    def rows(self, names: list[str], num_joints: int) -> dict[str, np.ndarray]:
        """The style table's rows aligned with `names` (`style_table.PLAIN` for a style without one)."""
        from .style_table import PLAIN

        rows = {
            "prior_source": PLAIN["prior_source"]((len(names), num_joints, 4)),
            "prior_mean": PLAIN["prior_mean"]((len(names), num_joints, 4)),
            "prior_map": PLAIN["prior_map"]((len(names), num_joints, 3, 3)),
            "prior_radius": PLAIN["prior_radius"]((len(names), num_joints)),
            "prior_on": PLAIN["prior_on"]((len(names),)),
        }
        for i, name in enumerate(names):
            if name in self.styles:
                k = self.styles.index(name)
                rows["prior_source"][i], rows["prior_mean"][i] = self.carry.source[k], self.carry.mean[k]
                rows["prior_map"][i], rows["prior_radius"][i] = self.carry.map[k], self.carry.radius[k]
                rows["prior_on"][i] = 1.0
        return rows

    def save(self, path: Path) -> Path:
        c = self.carry
        np.savez(path, styles=np.array(self.styles), source=c.source, mean=c.mean, map=c.map, radius=c.radius)
        return path

    @classmethod
    def load(cls, path: Path) -> OutputPrior:
        with np.load(path) as z:
            arrays = [np.ascontiguousarray(z[k], np.float64) for k in ("source", "mean", "map", "radius")]
            return cls(tuple(str(s) for s in z["styles"]), StyleCarry(*arrays))


def carry_rows(table, rotations: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The rotations (B, J, 4) of the rows that weigh a style with an output prior carried by it
    (`table`: a `StyleTable` with the prior's rows); other rows exactly as they were."""
    on = table.get("prior_on")
    if on is None:
        return rotations
    w = np.asarray(weights, np.float64) * on[None]
    rows = np.flatnonzero(w.any(axis=1))
    if len(rows) == 0:
        return rotations
    carry = StyleCarry(
        table.get("prior_source"), table.get("prior_mean"), table.get("prior_map"), table.get("prior_radius")
    )
    carried = carry(np.asarray(rotations[rows], np.float64), w[rows]).astype(rotations.dtype)
    # the joints the fit left fixed (radius pi for every style: Hips, legs) keep their own bits;
    # taken from the carry they would be renormalised in float64, a float32 ulp off
    joints = np.flatnonzero((table.get("prior_radius") < np.pi).any(axis=0))
    out = np.array(rotations, copy=True)
    out[np.ix_(rows, joints)] = carried[:, joints]
    return out


def fit(model, styles: list[str], dataset: str = "bandai-namco-2") -> OutputPrior:
    """The prior of `styles` from `model` (its carriage in place, no output prior); each style
    carries its `CARRIED` joints (the upper body for a style not listed), the rest left alone."""
    from ..eval.run import stylise

    clips = train_clips(dataset)
    every = LOCOMOTION["walk"] + LOCOMOTION["run"]
    model = model.with_own_styles()
    model.output_prior = None
    inputs = [m.slice(0, FIT_FRAMES) for m in clips("normal", every)]
    made, real = [], []
    for s in styles:
        outs = stylise(model, inputs, [model.styles().index(s)] * len(inputs))
        made.append(np.concatenate([o.rotations[SKIP_FRAMES:] for o in outs]).astype(np.float64))
        real.append(np.concatenate([m.rotations for m in clips(s, every)]).astype(np.float64))
    names = model.skeleton.names
    per_style = []
    for s, source, target in zip(styles, made, real):
        carried = CARRIED.get(s, UPPER_BODY)
        fixed = tuple(j for j, n in enumerate(names) if n not in carried)
        per_style.append(StyleCarry.fit([source], [target], fixed, source_floor=np.radians(SOURCE_FLOOR_DEG)))
    return OutputPrior(tuple(styles), StyleCarry.stack(per_style))


def main(argv: list[str]) -> None:
    """`STYLE ...` (default: active exhausted, the styles validation chose)."""
    import time

    import torch

    from ..settings import get_settings
    from .runtime import load

    torch.set_num_threads(1)
    t0 = time.time()
    folder = get_settings().weights_dir / "lpn"
    prior = fit(load(folder), argv or list(CARRIED))
    print(f"wrote {prior.save(folder / OUTPUT_PRIOR_FILE)} for {', '.join(prior.styles)} in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
