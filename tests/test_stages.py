"""The shared stage pipeline (`models/stages.py`) and LPN-FiLM's declared stages: each loads from
its file, runs in the declared order, keeps its own state apart, and can be switched off."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from models.interface import State
from models.motion.assets import bandai_namco_skeleton
from models.motion.skeleton import Skeleton
from models.stages import Pipeline, Rows, Stage, StageFrame


@pytest.fixture(scope="module")
def bn_skeleton() -> Skeleton:
    return bandai_namco_skeleton()


@contextmanager
def setting(monkeypatch: pytest.MonkeyPatch, name: str, value: str) -> Iterator[None]:
    """The settings read with the environment variable `name` set to `value` (the cached
    settings dropped on the way in and out, so a load inside sees it and one after does not)."""
    from models.settings import get_settings

    monkeypatch.setenv(name, value)
    get_settings.cache_clear()
    try:
        yield
    finally:
        monkeypatch.delenv(name, raising=False)
        get_settings.cache_clear()


class Counter:
    """A stateful toy stage: adds its per-style offset to every rotation, counts its frames."""

    def __init__(self, offsets: dict[str, float]) -> None:
        self.offsets = offsets

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        return {"offset": np.array([self.offsets.get(s, 0.0) if s else 0.0 for s in styles])}

    def init_state(self, batch: int) -> State:
        return {"frames": np.zeros(batch, np.int64)}

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        shift = frame.weights @ rows["offset"]
        moved = (frame.rotations + shift[:, None, None]).astype(frame.rotations.dtype)
        return moved, {"frames": state["frames"] + 1}

    def save(self, path: Path) -> Path:
        path.write_text(repr(self.offsets))
        return path


def test_a_pipeline_runs_its_stages_in_order_each_on_its_own_state(bn_skeleton):
    pipe = Pipeline((("a", Counter({"x": 1.0})), ("b", None), ("c", Counter({"y": 10.0}))))
    assert isinstance(pipe.a, Stage) and pipe.b is None
    state = pipe.init_state(2)
    assert set(state) == {"a/frames", "c/frames"}
    rows = pipe.rows(["x", None, "y"], bn_skeleton)
    np.testing.assert_array_equal(rows["a"]["offset"], [1.0, 0.0, 0.0])  # None: a row that changes nothing
    weights = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    frame = StageFrame(np.zeros((2, 1, 4)), weights, np.zeros(2), 0)
    out, state = pipe.step_batch(state, frame, rows)
    np.testing.assert_array_equal(out[:, 0, 0], [1.0, 10.0])
    np.testing.assert_array_equal(state["c/frames"], [1, 1])
    off = pipe.without("a")
    out, _ = off.step_batch(off.init_state(2), frame, off.rows(["x", None, "y"], bn_skeleton))
    np.testing.assert_array_equal(out[:, 0, 0], [0.0, 10.0])
    with pytest.raises(KeyError):
        pipe.replace(d=None)
    with pytest.raises(AttributeError):
        _ = pipe.d


def test_lpn_declares_each_stage_with_its_fit_and_loads_every_committed_one(bn_skeleton):
    from models.lpn.runtime import STAGES
    from models.settings import get_settings

    folder = get_settings().weights_dir / "lpn"
    full = Pipeline.load(STAGES, folder, bn_skeleton)
    core = Pipeline.load(STAGES, folder, bn_skeleton, core_only=True)
    for spec in STAGES:
        assert callable(spec.fit), spec.name
        stage = getattr(full, spec.name)
        assert (stage is not None) == (folder / spec.file).exists(), spec.name
        assert stage is None or isinstance(stage, Stage), spec.name
        assert getattr(core, spec.name) is None
    assert [k for k, _ in full.stages] == [s.name for s in STAGES]


def test_the_lpn_fit_command_refits_one_stage_for_one_style_and_keeps_the_others(tmp_path, monkeypatch):
    """`python -m models.lpn fit --stages arm_coupling active` on a copy of the weights: the
    file keeps every other style's rows bit for bit, active's are refitted, and it loads back."""
    import shutil

    from models.lpn.__main__ import main
    from models.lpn.runtime import STAGES
    from models.settings import get_settings

    folder = get_settings().weights_dir / "lpn"
    spec = next(s for s in STAGES if s.name == "arm_coupling")
    if not (folder / spec.file).exists():
        pytest.skip("no LPN-FiLM arm coupling committed")
    shutil.copytree(folder, tmp_path / "lpn")
    with setting(monkeypatch, "STYLESTREAM_WEIGHTS_DIR", str(tmp_path)):
        main(["fit", "--stages", "arm_coupling", "active"])
    skeleton = bandai_namco_skeleton()
    before, after = spec.load(folder / spec.file, skeleton), spec.load(tmp_path / "lpn" / spec.file, skeleton)
    assert sorted(after.styles) == sorted(before.styles)
    for style in before.styles:
        if style != "active":
            k, j = before.styles.index(style), after.styles.index(style)
            np.testing.assert_array_equal(after.walk[j], before.walk[k])
    assert np.isfinite(after.walk).all()


def test_lpn_each_stage_switched_off_changes_the_styled_output_and_the_core_has_none(lpn_model, bn_walk):
    """Every committed per-style stage moves an elderly walk (the hinge floor acts only on a limb
    bent past it: `test_hinge_floor.py`); with all of them off the step is the core's."""
    from models.lpn.runtime import LPNModel

    walk, w = bn_walk.slice(0, 45), lpn_model.weight_vector({"elderly": 1.0})
    full = lpn_model.run(walk, w)[0].rotations
    names = [k for k, s in lpn_model.stages.stages if s is not None]
    assert names, "no LPN-FiLM stage committed"
    for name in set(names) - {"hinge_floor"}:
        twin = lpn_model.with_own_styles()
        twin.stages = twin.stages.without(name)
        assert not np.array_equal(twin.run(walk, w)[0].rotations, full), name
    bare = lpn_model.with_own_styles()
    bare.stages = bare.stages.without(*names)
    core = LPNModel(lpn_model.p, lpn_model.skeleton, lpn_model.config)
    np.testing.assert_array_equal(bare.run(walk, w)[0].rotations, core.run(walk, w)[0].rotations)


def test_lpn_keeps_a_stateful_stages_state_in_the_session_state(lpn_model, bn_walk):
    """A stage's state lives in the session's state under "stage/key", starts fresh with the
    session and advances every step."""
    from models.interface import FrameBatch

    twin = lpn_model.with_own_styles()
    twin.stages = twin.stages.replace(hinge_floor=Counter({}))
    state = twin.init_state(2)
    assert state["hinge_floor/frames"].tolist() == [0, 0]
    w = np.zeros((2, len(twin.styles())), np.float32)
    for t in range(3):
        root, rot = (np.repeat(a[t : t + 1], 2, 0) for a in (bn_walk.translations[:, 1], bn_walk.rotations))
        _, state = twin.step_batch(state, FrameBatch(root, rot), w)
    assert state["hinge_floor/frames"].tolist() == [3, 3]


def test_a_setting_switches_an_lpn_stage_off_at_load(monkeypatch):
    """`STYLESTREAM_STAGES_OFF='["lpn.carriage"]'`: the loaded model runs without its carriage, the
    other stages on; a stage LPN-FiLM does not declare is an error."""
    from models.lpn import load
    from models.settings import get_settings

    folder = get_settings().weights_dir / "lpn"
    with setting(monkeypatch, "STYLESTREAM_STAGES_OFF", '["lpn.carriage", "erd.leaf_prior"]'):
        model = load(folder)
        assert model.stages.carriage is None and model.stages.output_prior is not None
    with setting(monkeypatch, "STYLESTREAM_STAGES_OFF", '["lpn.no_such_stage"]'), pytest.raises(KeyError):
        load(folder)


def test_erd_declares_each_stage_with_its_fit_and_a_setting_switches_one_off(bn_skeleton, monkeypatch):
    """Style-ERD's stages load from their committed files in the declared order, the core has
    none, and `STYLESTREAM_STAGES_OFF='["erd.leaf_prior"]'` loads the model without its leaf prior."""
    from models.erd import load
    from models.erd.stages import STAGES
    from models.settings import get_settings

    folder = get_settings().weights_dir / "erd"
    full = Pipeline.load(STAGES, folder, bn_skeleton)
    assert [k for k, _ in full.stages] == [s.name for s in STAGES]
    for spec in STAGES:
        assert callable(spec.fit), spec.name
        stage = getattr(full, spec.name)
        assert (stage is not None) == (folder / spec.file).exists(), spec.name
        assert stage is None or isinstance(stage, Stage), spec.name
    assert all(s is None for _, s in load(folder, core_only=True).stages.stages)
    with setting(monkeypatch, "STYLESTREAM_STAGES_OFF", '["erd.leaf_prior", "lpn.carriage"]'):
        model = load(folder)
        assert model.stages.leaf_prior is None and model.stages.output_prior is not None
        assert not any(k.startswith("leaf_prior/") for k in model.init_state(1))
    with setting(monkeypatch, "STYLESTREAM_STAGES_OFF", '["erd.no_such_stage"]'), pytest.raises(KeyError):
        load(folder)


def test_the_erd_fit_command_refits_one_stage_for_one_style_and_keeps_the_others(
    small_erd_cache, bn_skeleton, tmp_path, monkeypatch
):
    """`python -m models.erd fit --stages twist_range active` on a copy of the weights: the file
    keeps every other style's rows bit for bit, active's are refitted from its real TRAIN frames
    (those of the feature cache, here a few clips')."""
    import shutil

    from models.erd.__main__ import main
    from models.erd.dataset import STYLES
    from models.erd.rotation_prior import real_rotations
    from models.erd.stages import STAGES
    from models.erd.twist_range import TwistRange
    from models.settings import get_settings

    folder = get_settings().weights_dir / "erd"
    spec = next(s for s in STAGES if s.name == "twist_range")
    shutil.copytree(folder, tmp_path / "erd")
    with np.load(folder / spec.file) as z:  # another style's rows, to see the refit replace them
        np.savez(tmp_path / "erd" / spec.file, **{k: z[k][::-1] if k in ("mean", "lo", "hi") else z[k] for k in z})
    with setting(monkeypatch, "STYLESTREAM_WEIGHTS_DIR", str(tmp_path)):
        main(["fit", "--stages", "twist_range", "active"])
    before, after = spec.load(folder / spec.file, bn_skeleton), spec.load(tmp_path / "erd" / spec.file, bn_skeleton)
    want = TwistRange.fit(bn_skeleton, [real_rotations()[STYLES.index("active")]], ("active",))
    k = before.styles.index("active")
    for name in ("mean", "lo", "hi"):
        np.testing.assert_array_equal(getattr(after, name)[k], getattr(want, name)[0])
        assert not np.array_equal(getattr(after, name)[k], getattr(before, name)[::-1][k])
        others = [j for j in range(len(before.styles)) if j != k]
        np.testing.assert_array_equal(getattr(after, name)[others], getattr(before, name)[::-1][others])


def test_lti_declares_its_stages_and_each_switches_off_in_both_paths(monkeypatch):
    """LTI's stages (`models.lti.STAGES`) are on by default, all off for the core alone, and
    `STYLESTREAM_STAGES_OFF` switches one off at load; a translator of a model without the
    rotation prior or the raised arm has none either, so the offline path runs what the stream runs."""
    from models.lti import STAGES, load

    assert load().stages == STAGES and load(core_only=True).stages == ()
    with setting(monkeypatch, "STYLESTREAM_STAGES_OFF", '["lti.rotation_prior", "lti.raised_arm", "erd.leaf_prior"]'):
        model = load()
        assert model.stages == ("saturation", "hinge_floor", "foot_pitch", "root_give") and not model.raised_arms
        assert all(t.prior_mean is None and t.raised_arm is None for t in model.translators.values())
        assert load(core_only=True).hinges is None
    with setting(monkeypatch, "STYLESTREAM_STAGES_OFF", '["lti.no_such_stage"]'), pytest.raises(KeyError):
        load()
