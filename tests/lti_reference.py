"""A recorded reference of LTI's streaming step: a few validation clips streamed as a batch of
sessions (single styles, a mix, an intensity), with every stage on and the committed weights.
`tests/test_lti_step.py` checks that the step still gives these outputs to round-off, so a change
to how the step is computed (kernels, fusing, records) cannot change what it computes unnoticed.
The fixture was first written by the step as it was before it became one compiled call
(separate kernels per stage); rewrite it only after refitting weights or a deliberate change to
what a stage computes (then say so in the commit).

    .venv/bin/python -m tests.lti_reference      # rewrite tests/fixtures/lti_step_reference.npz
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def carry_entry(carry: np.ndarray, key: str) -> np.ndarray:
    """(B, *shape) view of one entry of a packed carry (`kernels.CARRY`)."""
    from models.lti.kernels import SPANS

    at, shape, _ = SPANS[key]
    return carry[:, at : at + int(np.prod(shape))].reshape(len(carry), *shape)


FIXTURE = Path(__file__).parent / "fixtures" / "lti_step_reference.npz"
CLIPS = (("walk", 0), ("wave-both-hands", 0), ("raise-up-left-hand", 0), ("run", 0))
FRAMES = 120
EVERY = 6  # outputs kept every EVERY frames (the state carries every frame into them)
# per session: {style: weight}
MIXES = ({"elderly": 1.0}, {"youthful": 1.0}, {"feminine": 0.6, "active": 0.4}, {"exhausted": 0.7})


def inputs(index) -> tuple[np.ndarray, np.ndarray]:
    """(T, B, 3) roots and (T, B, 22, 4) rotations of the reference clips, cut to `FRAMES`
    (a shorter clip holds its last frame)."""
    from models.data import load_motions, select
    from models.motion.bn_skeleton import HIPS

    clips = [select(index, dataset="bandai-namco-2", split="val", style="normal", content=c)[k] for c, k in CLIPS]
    motions = [m.slice(0, FRAMES) for m in load_motions(clips)]
    held = lambda a: np.concatenate([a, np.repeat(a[-1:], FRAMES - len(a), 0)])  # noqa: E731
    root = np.stack([held(m.translations[:, HIPS]) for m in motions], axis=1).astype(np.float64)
    rot = np.stack([held(m.rotations) for m in motions], axis=1).astype(np.float64)
    return root, rot


def weights(styles: list[str]) -> np.ndarray:
    w = np.zeros((len(MIXES), len(styles)))
    for b, mix in enumerate(MIXES):
        for s, v in mix.items():
            w[b, styles.index(s)] = v
    return w


def stream(model, root: np.ndarray, rot: np.ndarray) -> dict[str, np.ndarray]:
    """Every `EVERY`-th output frame of the sessions streamed together."""
    from models.interface import FrameBatch

    w = weights(model.styles())
    state = model.init_state(root.shape[1])
    out: dict[str, list] = {"root": [], "rotations": [], "contacts": []}
    for t in range(len(root)):
        frame, state = model.step_batch(state, FrameBatch(root[t], rot[t]), w)
        if t % EVERY == 0:
            out["root"].append(frame.root)
            out["rotations"].append(frame.rotations)
            out["contacts"].append(frame.contacts)
    return {k: np.stack(v) for k, v in out.items()}


def unpacked(state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`state` as the step kept it before its carry was packed (`kernels.CARRY`): each entry
    under its own key, with its own dtype; the styles' x as they are."""
    from models.lti.kernels import CARRY
    from models.lti.model import CARRY as KEY
    from models.motion.feet import STATE_SHAPES

    dtypes = {"started": bool, **{k: dtype for k, (_, dtype) in STATE_SHAPES.items()}}
    old = {k: carry_entry(state[KEY], k).astype(dtypes.get(k, np.float64)) for k in CARRY}
    return {**old, **{k: v for k, v in state.items() if k != KEY}}


def recorded_model():
    """The model the reference is recorded with: every stage on but the hinge floors, the
    input's saturation, the feet's pitch and the root giving way, its planter holding hinted feet
    no further than others (they came after the reference; `test_lti`'s offline mix and
    streaming-equals-offline, `test_lti_saturation` and `test_feet` check them)."""
    from dataclasses import replace

    from models.lti import WEIGHTS_DIR, LTIStyleModel

    model = LTIStyleModel(weights_dir=WEIGHTS_DIR, off=("hinge_floor", "saturation", "foot_pitch", "root_give"))
    model.planter = replace(model.planter, hint_offset=None)
    model._set_styles(model.styles())  # the step's records carry the planter's settings
    return model


def main() -> None:
    from models.data import build_index

    root, rot = inputs(build_index(["bandai-namco-2"]))
    np.savez_compressed(FIXTURE, **stream(recorded_model(), root, rot))
    print(FIXTURE, FIXTURE.stat().st_size, "bytes")


if __name__ == "__main__":
    main()
