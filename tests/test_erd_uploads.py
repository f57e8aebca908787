"""Style-ERD styles from one uploaded clip (`models/erd/uploads.py`): streamable at once, moving
the output toward the clip's statistics, leaving the trained styles and running sessions as they
were, saved and loaded again; the job's fitted branch (`finetune.py`, slow)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from models.interface import FrameBatch, style_vector  # noqa: E402
from models.motion.rotation_ball import comparable  # noqa: E402
from models.motion.rotations import quat_angle, quat_mean  # noqa: E402


@pytest.fixture
def model(erd_model):
    return erd_model


@pytest.fixture(scope="module")
def clips():
    """A real dataset-1 `proud` walk (a style Style-ERD never trained on) and a dataset-2 neutral walk."""
    try:
        from models.data import build_index, load_motions, select

        index = build_index(["bandai-namco-1", "bandai-namco-2"])
        upload = sorted(select(index, dataset="bandai-namco-1", style="proud", content="walk"), key=lambda c: c.name)
        neutral = select(index, dataset="bandai-namco-2", split="val", style="normal", content="walk")
        clip, walk = load_motions([upload[0], neutral[0]])
    except Exception as exc:  # noqa: BLE001  (dataset not unpacked on this machine)
        pytest.skip(f"Bandai Namco datasets unavailable: {exc}")
    return clip, walk.slice(0, 120)


def stream(model, motion, weights: np.ndarray) -> np.ndarray:
    state, out = model.init_state(1), []
    for t in range(motion.num_frames):
        frame, state = model.step_batch(
            state, FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1]), weights[None]
        )
        out.append(frame.rotations[0])
    return np.array(out)


def mean_distance(rotations: np.ndarray, reference: np.ndarray) -> float:
    """Mean over joints of the angle between the two clips' mean local rotations (Hips without heading)."""
    a, b = quat_mean(comparable(rotations), axis=0), quat_mean(comparable(reference), axis=0)
    return float(np.mean(quat_angle(a, b)))


def test_an_upload_streams_at_once_and_moves_toward_the_clip(model, clips):
    clip, walk = clips
    mine = model.with_own_styles()
    mine.install_style("up", mine.style_from_clip(clip))
    assert mine.styles() == [*model.styles(), "up"] and "up" not in model.styles()
    out = stream(mine, walk, style_vector(mine, {"up": 1.0}))
    assert np.all(np.isfinite(out))
    before, after = mean_distance(walk.rotations, clip.rotations), mean_distance(out, clip.rotations)
    assert after < 0.7 * before, (before, after)


def test_trained_styles_stream_as_before_an_upload(model, clips):
    clip, walk = clips
    mine = model.with_own_styles()
    mine.install_style("up", mine.style_from_clip(clip))
    w = style_vector(model, {"elderly": 1.0})
    np.testing.assert_array_equal(stream(mine, walk, np.append(w, 0.0)), stream(model, walk, w))


def test_a_running_session_carries_on_across_an_upload_and_its_removal(model, clips):
    clip, walk = clips
    mine = model.with_own_styles()
    state = mine.init_state(1)
    frame = FrameBatch(walk.translations[:1, 1], walk.rotations[:1])
    _, state = mine.step_batch(state, frame, style_vector(mine, {"active": 1.0})[None])
    mine.install_style("up", mine.style_from_clip(clip))
    state = mine.upgrade_state(state)
    assert {"h.up", "c.up"} <= state.keys()
    out, state = mine.step_batch(state, frame, style_vector(mine, {"up": 0.5, "active": 0.5})[None])
    assert np.all(np.isfinite(out.rotations))
    mine.remove_style("up")
    state = mine.upgrade_state(state)
    assert not {"h.up", "c.up"} & state.keys()
    mine.step_batch(state, frame, style_vector(mine, {"active": 1.0})[None])


def test_a_saved_upload_loads_back_the_same(model, clips, tmp_path):
    clip, walk = clips
    style = model.style_from_clip(clip)
    model.save_style(style, tmp_path)
    assert model.has_saved_style(tmp_path)
    a, b = model.with_own_styles(), model.with_own_styles()
    a.install_style("up", style)
    b.install_style("up", model.load_style("up", tmp_path))
    w = style_vector(a, {"up": 1.0})
    np.testing.assert_array_equal(stream(a, walk.slice(0, 30), w), stream(b, walk.slice(0, 30), w))


def test_the_job_pairs_neutral_clips_from_the_mocap_without_the_feature_cache(model, clips, tmp_path, monkeypatch):
    """A fresh server has no TRAIN feature cache: the job's neutral clips are computed from the
    mocap, the nearest in what they do first, and no cache is built for them."""
    from models.erd import dataset, finetune

    monkeypatch.setattr(dataset, "cache_dir", lambda: tmp_path)
    neutral = finetune.features(model.maker, finetune.neutral_motions())
    x_clip, _ = model.maker.sequence(clips[0].translations[:, 1], clips[0].rotations)
    paired = [neutral[i] for i in finetune.pair_order(neutral, x_clip, finetune.PAIRS)]
    assert len(paired) == finetune.PAIRS and all(len(c) > finetune.WINDOW for c in paired)
    gaps = [np.linalg.norm(finetune.descriptor(c) - finetune.descriptor(x_clip)) for c in neutral]
    assert np.linalg.norm(finetune.descriptor(paired[0]) - finetune.descriptor(x_clip)) < np.median(gaps)
    assert not any(tmp_path.iterdir())


def test_without_the_mocap_a_fine_tuning_upload_is_refused_typed(model, tmp_path, monkeypatch):
    from models.interface import StyleRejected
    from models.settings import Settings

    empty = Settings(data_dir=tmp_path, cache_dir=tmp_path)
    monkeypatch.setattr("models.settings.get_settings", lambda: empty)
    monkeypatch.setattr("models.data.archives.get_settings", lambda: empty)
    model.check_upload(300, fine_tune=False)  # the instant style needs no data
    with pytest.raises(StyleRejected) as refused:
        model.check_upload(300, fine_tune=True)
    assert refused.value.code == "training_data_unavailable"


@pytest.mark.slow
def test_the_job_fits_a_branch_that_brings_held_out_neutral_clips_closer(model, clips, tmp_path, monkeypatch):
    """The job tunes on neutral clips from the mocap alone: the feature cache folder is empty, as
    on a fresh server."""
    from models.erd import dataset

    monkeypatch.setattr(dataset, "cache_dir", lambda: tmp_path)
    clip, walk = clips
    seen: list[float] = []
    tuned = model.fine_tune_style("up", clip, lambda fraction, message: seen.append(fraction), 0)
    assert tuned.style is not None and seen == sorted(seen)
    assert tuned.summary["held_out_loss_fitted"] < tuned.summary["held_out_loss_start"]
    mine = model.with_own_styles()
    mine.install_style("up", tuned.style)
    assert np.all(np.isfinite(stream(mine, walk.slice(0, 30), style_vector(mine, {"up": 1.0}))))
    assert not any(tmp_path.iterdir())  # no feature cache was built for it
