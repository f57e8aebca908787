"""Style-ERD's runs toward feminine and active: the upper arms swing with the thighs as in the
style's real runs (`ARM_COUPLING_FILE` beside the weights, written by
`python -m models.erd.arm_coupling [STYLE ...]`; `runtime.ERDModel` and `offline.stylise` apply
it after the output prior and before the clamp into the style's range).

Toward feminine the run output prior stilled the upper arms. On the validation runs (right / left,
degrees/s), the network swung them at 94 / 164, the prior left 51 / 72 and the output 39 / 63; the
real feminine runs swing at 120 / 131. The prior's map has gains 0.29-0.51 along one axis of the
upper arm and 2.0-2.5 along another, and a map that scales each joint along its axes cannot turn a
swing onto another axis. In the real feminine TRAIN runs the upper arm's deviation from its mean is,
to R^2 0.75 / 0.92 / 0.62 per axis, a linear function of the two thighs'.
`models.motion.coupling` gives the output's upper arms the real runs' relation to the thighs
(`LINKS`), by the frame's run share (`gait.py`; walks are not coupled).
- Fitted on the style's real TRAIN runs, and on the output driven by the `normal` TRAIN runs (every
  prior in place, no coupling).
- Upper arms toward feminine on the validation runs: 115 / 126 degrees/s.

Chosen on the validation runs (model card):
- **Rotation judge margins** (log p(style) minus the best other style's): toward feminine
  0.39-1.88 -> 0.82-2.45, toward active 0.01-1.90 -> 0.30-2.17. Every validation cell stayed as it
  was.
- **Other styles:** toward youthful, elderly and exhausted the margins fell, and toward masculine
  nothing changed, so they are not coupled.
- **More drivers** (the chest and the shoulder as well): the margins rose further (feminine
  1.04-2.66). But the regression's larger gains passed the drivers' frame-to-frame noise into the
  arm: feminine's left upper arm turned faster from one frame to the next than the real p99.9 in
  10.7 % of frames, against 2.6 % without the coupling and 1.6 % with the thighs alone.
- **The forearms coupled as well** (to the upper arm, shoulder and chest): they overshot the real
  speed, 238 / 153 against 147 / 102 degrees/s.
"""

from __future__ import annotations

import sys

import numpy as np

from ..motion.coupling import Coupling, Link, write_coupling

ARM_COUPLING_FILE = "arm_coupling.npz"
COUPLED = ("feminine", "active")  # the styles validation chose (module doc)
LINKS: tuple[Link, ...] = tuple((f"UpperArm_{s}", ("UpperLeg_L", "UpperLeg_R")) for s in "LR")
FIT_FRAMES = 300
SKIP_FRAMES = 30  # the output's first second settles from the input's first pose


def fit(model, styles: list[str], dataset: str = "bandai-namco-2") -> Coupling:
    """The coupling of `styles` from `model` (every prior in place, no coupling), on runs alone."""
    from ..data import build_index, load_motions, select
    from ..eval.run import stylise

    index = build_index([dataset])

    def runs(style: str) -> list:
        return load_motions([c for c in select(index, split="train", style=style) if c.content == "run"])

    saved, model.arm_coupling = model.arm_coupling, None
    try:
        inputs = [m.slice(0, FIT_FRAMES) for m in runs("normal")]

        def made(style: str, gait: str) -> list[np.ndarray]:
            outs = stylise(model, inputs, [model.styles().index(style)] * len(inputs))
            return [o.rotations[SKIP_FRAMES:] for o in outs]

        def real(style: str, gait: str) -> list[np.ndarray]:
            return [m.rotations for m in runs(style)]

        return Coupling.fit(styles, LINKS, model.skeleton.names, real, made, gaits=("run",))
    finally:
        model.arm_coupling = saved


def main(argv: list[str]) -> None:
    """`STYLE ...` (default: `COUPLED`): refits those, keeping the file's other styles."""
    import time

    import torch

    from ..settings import get_settings
    from .runtime import load

    torch.set_num_threads(1)
    t0 = time.time()
    folder = get_settings().weights_dir / "erd"
    path = folder / ARM_COUPLING_FILE
    coupling = write_coupling(fit(load(folder), argv or list(COUPLED)), path, keep_others=bool(argv))
    print(f"wrote {path} for {', '.join(coupling.styles)} in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
