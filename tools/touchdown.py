"""`python -m tools.touchdown [--methods lti erd lpn] [--styles ...]`: why feet skid as they land.

The skid column (`metrics.touchdown_speeds`) says how often a foot lands flat while still moving;
this says why, on dataset 2's neutral VALIDATION walks toward each style (each method's core alone,
as `models.registry` serves it), beside the real style's validation walks:
- **relative speed**: at each touchdown, the ankle's speed relative to the hips along the hips'
  travel (cm/s; the median). A real foot lands as it moves back under the body (about minus the
  walking speed); a foot still swinging forward (> 0) lands flat at the swing's forward end and skids.
- **reach**: the shank's forward tilt at its most forward (the clip's p95 of its world pitch, degrees,
  + = ankle ahead of the knee): the stride's reach before heel strike.
"""

from __future__ import annotations

import argparse

import numpy as np

from models.data import build_index, load_motions, select
from models.eval.metrics import SKID_SPEED, flat_foot_contacts, touchdown_speeds, touchdowns
from models.eval.run import DATASET, INPUT_STYLE, stylise_toward
from models.motion.features import body_joint, left_leg_length
from models.motion.skeleton import Motion
from models.registry import METHODS, load_model
from models.settings import get_settings

STYLES = ("active", "elderly", "exhausted", "feminine", "masculine", "youthful")


def _travel(motion: Motion, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 2) hips ground positions and (F, 2) unit travel directions (the hips' smoothed velocity)."""
    hips = pos[:, body_joint(motion.skeleton, "hips"), :][:, [0, 2]]
    v = np.gradient(hips, axis=0)
    v = np.apply_along_axis(lambda x: np.convolve(x, np.ones(9) / 9, mode="same"), 0, v)
    return hips, v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)


def landings(motion: Motion, positions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per touchdown (`metrics.touchdowns`): the foot's speed over the ground
    (`metrics.touchdown_speeds`) and the ankle's speed relative to the hips along their travel,
    both in cm/s (units/s)."""
    pos = motion.global_positions() if positions is None else positions
    contacts, speeds = flat_foot_contacts(motion, pos)
    hips, direction = _travel(motion, pos)
    ankles = pos[:, [body_joint(motion.skeleton, f"ankle_{side}") for side in "lr"]][..., [0, 2]]
    rel = np.gradient(ankles - hips[:, None], axis=0) * motion.fps  # (F, 2 feet, 2)
    feet, frames = touchdowns(contacts)
    relative = np.einsum("ni,ni->n", rel[frames, feet], direction[frames])
    return touchdown_speeds(contacts, speeds), relative


def reach(motion: Motion, positions: np.ndarray | None = None) -> float:
    """p95 over the clip of the left shank's forward tilt along the hips' travel (degrees)."""
    pos = motion.global_positions() if positions is None else positions
    _, direction = _travel(motion, pos)
    names = motion.skeleton.names
    shank = pos[:, names.index("Foot_L")] - pos[:, names.index("LowerLeg_L")]
    forward = np.einsum("fi,fi->f", shank[:, [0, 2]], direction)
    return float(np.percentile(np.degrees(np.arctan2(forward, -shank[:, 1])), 95))


def summary(motions: list[Motion]) -> str:
    positions = [m.global_positions() for m in motions]
    ground, relative = (np.concatenate(x) for x in zip(*(landings(m, p) for m, p in zip(motions, positions))))
    leg = left_leg_length(motions[0].skeleton)
    skid = float(np.mean(ground > SKID_SPEED * leg)) if len(ground) else 0.0
    return (
        f"skid {100 * skid:3.0f}% of {len(ground):3d} | relative speed {np.median(relative):+6.0f} cm/s | "
        f"reach {np.mean([reach(m, p) for m, p in zip(motions, positions)]):+5.1f} deg"
    )


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.touchdown", description=__doc__)
    ap.add_argument("--methods", nargs="*", default=list(METHODS))
    ap.add_argument("--styles", nargs="*", default=list(STYLES))
    args = ap.parse_args()
    index = build_index([DATASET])
    walks = lambda style: load_motions(select(index, split="val", style=style, content="walk"))  # noqa: E731
    inputs = walks(INPUT_STYLE)
    print(f"{'input':22s} {summary(inputs)}")
    for style in args.styles:
        print(f"{'real ' + style:22s} {summary(walks(style))}")
    for method in args.methods:
        model = load_model(get_settings().weights_dir, method, core_only=True)
        if model is None:
            continue
        outs = stylise_toward(model, inputs, args.styles)
        for style in args.styles:
            print(f"{method + ' core ' + style:22s} {summary(outs[style])}", flush=True)


if __name__ == "__main__":
    main()
