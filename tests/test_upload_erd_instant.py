"""Style-ERD's instant upload on real clips (`models/erd/uploads.py`, `upload_stages.py`): a
style made from one dataset-1 walk moves a dataset-2 neutral walk's clip statistics (the style
judge's: local rotations and angular speeds) toward the uploaded clip's, where a trained style's
branch had pushed them toward that style instead; its prior carries from what the network makes
of neutral clips like the upload."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from models.motion.rotations import quat_exp  # noqa: E402
from models.motion.style_carry import tangent_stats  # noqa: E402


@pytest.fixture
def model(erd_model):
    return erd_model


@pytest.fixture(scope="module")
def clips():
    """Real dataset-1 walks of styles Style-ERD never trained on, and a dataset-2 neutral walk."""
    try:
        from models.data import build_index, load_motions, select

        index = build_index(["bandai-namco-1", "bandai-namco-2"])
        uploads = [
            sorted(select(index, dataset="bandai-namco-1", style=s, content="walk"), key=lambda c: c.name)[0]
            for s in ("giant", "not-confident")
        ]
        neutral = select(index, dataset="bandai-namco-2", split="val", style="normal", content="walk")[0]
        *styled, walk = load_motions([*uploads, neutral])
    except Exception as exc:  # noqa: BLE001  (dataset not unpacked on this machine)
        pytest.skip(f"Bandai Namco datasets unavailable: {exc}")
    return styled, walk


def statistics(motion) -> np.ndarray:
    """The style judge's clip statistics, averaged over the clip, in its standardisation."""
    from models.eval.style_judge import clip_statistics, load_style_judge

    return clip_statistics(motion).mean(0) / load_style_judge().scale


def test_an_instant_upload_moves_a_neutral_walk_toward_the_clip(model, clips):
    from models.eval.run import stylise

    styled, walk = clips
    for clip in styled:
        mine = model.with_own_styles()
        mine.install_style("up", mine.style_from_clip(clip))
        out = stylise(mine, [walk], [mine.styles().index("up")])[0]
        target = statistics(clip)
        before = np.linalg.norm(statistics(walk) - target)
        after = np.linalg.norm(statistics(out) - target)
        assert after < 0.8 * before, (before, after)


def test_the_prior_carries_from_neutral_clips_of_the_uploads_pace(model, clips):
    """The source is pooled from the neutral clips nearest the upload in what it does: for a
    walk, slower than the neutral clips' average pace (runs among them) and turning little."""
    from models.erd.upload_stages import PAIRS, descriptor

    styled, _ = clips
    x, _ = model.maker.sequence(styled[0].translations[:, 1], styled[0].rotations)
    paired = model.sources.descriptor
    gap = np.linalg.norm((paired - descriptor(x)) / paired.std(0), axis=1)
    near = np.argsort(gap)[:PAIRS]
    assert gap[near].max() < np.median(gap)
    assert abs(paired[near, 0].mean() - descriptor(x)[0]) < abs(paired[:, 0].mean() - descriptor(x)[0])


def test_pooled_clip_gaussians_match_the_gaussian_of_their_frames():
    """What the upload's source pools from the stored per-clip Gaussians is the Gaussian of all
    their frames together: each clip's spread plus its mean's offset."""
    from models.erd.upload_stages import pooled

    rng = np.random.default_rng(0)
    clips = [quat_exp(rng.normal(0, 0.1, (1, 4, 3)) + rng.normal(0, 0.05, (300, 4, 3))) for _ in range(5)]
    fitted = [tangent_stats(c) for c in clips]
    mean, cov = pooled(np.stack([f[0] for f in fitted]), np.stack([f[1] for f in fitted]), np.full(5, 300.0))
    whole_mean, whole_cov, _ = tangent_stats(np.concatenate(clips))
    np.testing.assert_allclose(np.abs(np.sum(mean * whole_mean, -1)), 1.0, atol=1e-5)
    np.testing.assert_allclose(cov, whole_cov, atol=1e-4)


def test_a_lively_upload_keeps_the_trunks_motion(model):
    """The prior's floor guards its slow map; the frame-to-frame part keeps the network's motion
    where the clip moves as much: a `happy` walk's upload leaves the trunk and head turning at 44 %
    of the neutral input's angular speed (the floored map's fast gains left 29 %)."""
    from models.data import build_index, load_motions, select
    from models.eval.run import stylise
    from models.motion.rotations import quat_angle

    try:
        index = build_index(["bandai-namco-1", "bandai-namco-2"])
        happy = sorted(select(index, dataset="bandai-namco-1", style="happy", content="walk"), key=lambda c: c.name)
        neutral = select(index, dataset="bandai-namco-2", split="val", style="normal", content="walk")[0]
        clip, walk = load_motions([happy[0], neutral])
    except Exception as exc:  # noqa: BLE001  (dataset not unpacked on this machine)
        pytest.skip(f"Bandai Namco datasets unavailable: {exc}")
    mine = model.with_own_styles()
    mine.install_style("up", mine.style_from_clip(clip))
    out = stylise(mine, [walk], [mine.styles().index("up")])[0]
    trunk = [walk.skeleton.index(n) for n in ("Spine", "Chest", "Neck", "Head")]

    def speed(q: np.ndarray) -> float:
        return float(quat_angle(q[1:, trunk], q[:-1, trunk]).mean())

    assert speed(out.rotations) > 0.36 * speed(walk.rotations), (speed(out.rotations), speed(walk.rotations))
