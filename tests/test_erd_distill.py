"""Style-ERD distillation (`models/erd/distill.py`, `train.py --distill`): the targets are what
the shipped pipeline streams, a run trains toward them, and a network trained on its own twists
is decoded with them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.erd.dataset import STYLES, TARGET_STYLES  # noqa: E402 (after the torch check)
from models.motion.rotations import quat_angle  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO / "models" / "weights" / "erd"


@pytest.fixture(scope="module")
def model():
    from models.erd.runtime import load

    torch.set_num_threads(1)
    return load(WEIGHTS)


@pytest.fixture(scope="module")
def clips():
    """One validation walk per style, the neutral one first."""
    try:
        from models.data import build_index, select

        index = build_index(["bandai-namco-2"])
        return [select(index, split="val", style=s, content="walk")[0] for s in STYLES]
    except Exception as exc:  # dataset not unpacked on this machine
        pytest.skip(f"Bandai Namco dataset 2 unavailable: {exc}")


def test_targets_are_the_shipped_pipelines_rotations(model, clips):
    from models.data import load_motion
    from models.erd.distill import teacher_rotations

    from .reference.erd_offline import stylise

    motion = load_motion(clips[0]).slice(0, 40)
    got = teacher_rotations(model, motion)
    assert got.shape == (len(TARGET_STYLES), 40, 21, 4)
    gen = model.torch_generator().eval()
    for s in (1, 4):
        w = np.eye(len(TARGET_STYLES))[s]
        want = stylise(gen, model, motion, w, foot_lock=False).rotations
        assert np.degrees(quat_angle(got[s][:, 1:], want[:, 2:])).max() < 1e-3  # below the Hips
        assert np.degrees(quat_angle(got[s][:, 0], want[:, 1])).mean() > 1e-3  # the Hips lose their heading


def test_network_twists_decode_the_decoders_leaves(model, clips):
    from models.data import load_motion
    from models.motion.twist import transfer_twist

    motion = load_motion(clips[0]).slice(0, 2)
    rot_in = motion.rotations[:1]
    decoded = transfer_twist(motion.skeleton, rot_in, rot_in)  # then turned: every joint off the input
    decoded = decoded * np.array([1.0, 1.0, 1.0, 3.0])
    decoded /= np.linalg.norm(decoded, axis=-1, keepdims=True)
    from models.erd.runtime import load

    core = load(WEIGHTS, core_only=True)
    args = (core.stages.init_state(1), rot_in, decoded, np.ones((1, 6)) / 6, np.zeros(1))
    core.network_twists = False
    inputs = core.stage_batch(*args)[0]
    core.network_twists = True
    own = core.stage_batch(*args)[0]
    hand = model.skeleton.index("Hand_L")
    assert quat_angle(inputs[0, hand], rot_in[0, hand]) < 1e-9
    assert quat_angle(own[0, hand], decoded[0, hand]) < 1e-9
    assert quat_angle(own[0, hand], rot_in[0, hand]) > 0.01


def test_a_run_measures_the_distillation_term(model, clips, small_erd_cache, tmp_path):
    from models.data import load_motion
    from models.erd.carry import pack, unpack
    from models.erd.distill import split_targets
    from models.erd.train import main

    packed = pack(tmp_path / "erd.npz", {"train": clips, "val": clips[::2]})
    split = unpack(packed)[0]["train"]
    by_name = {c.name: c for c in clips}
    frames, targets = split_targets(model, split, lambda name: load_motion(by_name[name]))
    assert len(frames) == split.lengths[0] and targets.shape == (len(frames), 6, 21, 4)
    np.savez(tmp_path / "distill.npz", frames=frames, targets=targets)
    run = tmp_path / "run"
    args = [f"--data={packed}", f"--run_dir={run}", f"--out_dir={run / 'out'}", "--clf_iters=2", "--batch=16"]
    args += ["--eval_every=3", "--render_every=0", "--p_neutral=1", f"--init_weights={WEIGHTS}"]
    main([*args, "--max_iters=3", f"--distill={tmp_path / 'distill.npz'}", "--w_distill=1", "--network_twists=true"])
    history = torch.load(run / "ckpt.pt", weights_only=False)["history"]
    assert history[0]["train_distill"] > 1e-3  # the term is measured and trained on
