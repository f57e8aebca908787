"""Style-ERD training infrastructure: the packed training set (`models/erd/carry.py`) rebuilds the
cache's features, and a run stopped and resumed (`--resume`) ends where an uninterrupted run does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.erd.carry import decode, encode, pack  # noqa: E402 (after the torch check)
from models.erd.dataset import STYLES, load_stats  # noqa: E402


@pytest.fixture(scope="module")
def clips(small_erd_cache):
    """One validation walk per style (every style present, so the per-style priors exist); the
    pack's normalisation comes from the test feature cache."""
    from models.data import build_index, select

    index = build_index(["bandai-namco-2"])
    return [select(index, split="val", style=s, content="walk")[0] for s in STYLES]


@pytest.fixture(scope="module")
def packed(clips, tmp_path_factory) -> Path:
    return pack(tmp_path_factory.mktemp("carry") / "erd.npz", {"train": clips, "val": clips[::2]})


def test_encoding_keeps_rotations_within_a_thousandth_of_a_radian(clips):
    from models.data import load_motion
    from models.motion.rotations import quat_angle

    ref = load_stats()["ref"]
    q = load_motion(clips[2]).rotations
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    got = decode(*encode(q, ref), ref)
    assert quat_angle(got, q).max() < 1e-3


def test_unpacked_features_are_the_features_of_the_clips(clips, packed):
    from models.data import load_motions
    from models.erd.carry import unpack
    from models.erd.features import CONTACT, FeatureMaker

    splits, stats = unpack(packed)
    motions = load_motions(clips)
    maker = FeatureMaker(motions[0].skeleton, stats["ref"])
    want = np.concatenate([maker.sequence(m.translations[:, 1], m.rotations)[0] for m in motions])
    got = splits["train"].feats
    assert got.shape == want.shape
    err = np.abs(got - want) / stats["std"]
    assert np.percentile(err, 99.9) < 0.1  # quantisation only
    assert (got[:, CONTACT] != want[:, CONTACT]).mean() < 0.01  # a contact on its threshold may flip
    assert [STYLES[k] for k in splits["train"].style] == list(STYLES)


def _run(packed: Path, run_dir: Path, max_iters: int, resume: bool, seed: int = 1234) -> dict:
    from models.erd.train import main

    main(
        [
            f"--data={packed}",
            f"--run_dir={run_dir}",
            f"--out_dir={run_dir / 'out'}",
            f"--max_iters={max_iters}",
            "--schedule_iters=6",
            "--clf_iters=2",
            "--batch=8",
            "--eval_every=1000",
            "--ckpt_every=1000",
            "--render_every=0",
            "--w_hinge=1",
            f"--seed={seed}",
        ]
        + (["--resume"] if resume else [])
    )
    return torch.load(run_dir / "ckpt.pt", weights_only=False)


def test_a_resumed_run_ends_where_an_uninterrupted_one_does(packed, tmp_path):
    torch.set_num_threads(1)
    whole = _run(packed, tmp_path / "whole", 4, resume=False)
    _run(packed, tmp_path / "split", 2, resume=False)
    # another seed: only the restored generators (sampler, torch, python) can give the same batches
    resumed = _run(packed, tmp_path / "split", 4, resume=True, seed=99)
    assert whole["iter"] == resumed["iter"] == 4
    assert whole["schedule"]["by_steps"] and resumed["schedule"]["total"] == whole["schedule"]["total"] == 6
    for net in ("generator", "discriminator"):
        for k, v in whole[net].items():
            assert torch.allclose(v, resumed[net][k], atol=1e-6), (net, k)
    a, b = whole["opt_g"]["state"], resumed["opt_g"]["state"]
    assert all(torch.allclose(a[i]["exp_avg"], b[i]["exp_avg"], atol=1e-7) for i in a)


def test_a_run_measures_the_smoothness_term_on_augmented_windows(packed, tmp_path):
    from models.erd.train import main
    from models.settings import REPO_ROOT

    run = tmp_path / "run"
    args = [f"--data={packed}", f"--run_dir={run}", f"--out_dir={run / 'out'}", "--clf_iters=2", "--batch=16"]
    args += ["--eval_every=2", "--render_every=0", f"--init_weights={REPO_ROOT / 'models' / 'weights' / 'erd'}"]
    main([*args, "--max_iters=2", "--p_aug=1", "--w_smooth=1", "--w_teacher=1", "--teacher_vel=false"])
    history = torch.load(run / "ckpt.pt", weights_only=False)["history"]
    # the trained network reacts to turned and shaken inputs: the terms are measured and trained on
    assert history[0]["train_smooth"] > 0 and history[0]["train_teacher"] > 0 and history[0]["train_rot"] > 1e-3
