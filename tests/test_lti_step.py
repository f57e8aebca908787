"""LTI's streaming step computes what it computed before it was fused into one compiled call:
the recorded reference (`tests/lti_reference.py`) to round-off, every stage on; and the
reference exercises every stage (switching one off changes it). The hinge floors, the input's
saturation, the feet's pitch and the root giving way to held feet came after the reference was
recorded: it is compared with them off, and the numpy references check them (`test_lti`'s
offline mix and streaming-equals-offline, `test_lti_saturation`, `test_feet`)."""

from __future__ import annotations

import numpy as np
import pytest

from models.lti import WEIGHTS_DIR, LTIStyleModel, load

from .lti_reference import FIXTURE, inputs, recorded_model, stream


@pytest.fixture(scope="module")
def reference(index):
    with np.load(FIXTURE) as z:
        want = {k: z[k] for k in z}
    return inputs(index), want


def _recorded() -> LTIStyleModel:
    return recorded_model()


def test_the_step_equals_the_recorded_reference(reference):
    (root, rot), want = reference
    got = stream(_recorded(), root, rot)
    np.testing.assert_allclose(got["root"], want["root"], atol=1e-8)
    np.testing.assert_allclose(got["rotations"], want["rotations"], atol=1e-9)
    assert np.array_equal(got["contacts"], want["contacts"])


@pytest.mark.parametrize("stage", ["raised_arm", "footlock"])
def test_every_stage_shows_in_the_reference(reference, stage):
    (root, rot), want = reference
    off = {"footlock": False} if stage == "footlock" else {"off": (stage,)}
    got = stream(LTIStyleModel(weights_dir=WEIGHTS_DIR, **off), root, rot)
    assert np.abs(got["rotations"] - want["rotations"]).max() > 1e-3


def test_a_large_batch_gives_the_same(reference, monkeypatch):
    """From `COMPACT_FROM` sessions on, the step sees only the LTI states of the styles in use,
    and a style's sessions are stepped `CHUNK` at a time: the reference's sessions 36 times over
    (144 sessions, 36 on each style) give the reference 36 times."""
    import models.lti.model as lti_model
    from models.lti.kernels import CHUNK

    from . import lti_reference

    (root, rot), want = reference
    copies = 36
    assert 4 * copies >= lti_model.COMPACT_FROM and copies > CHUNK
    monkeypatch.setattr(lti_reference, "MIXES", lti_reference.MIXES * copies)
    got = stream(_recorded(), np.tile(root, (1, copies, 1)), np.tile(rot, (1, copies, 1, 1)))
    for k in range(copies):
        rows = slice(4 * k, 4 * k + 4)
        np.testing.assert_allclose(got["rotations"][:, rows], want["rotations"], atol=1e-9)
        np.testing.assert_allclose(got["root"][:, rows], want["root"], atol=1e-8)


def _resumes_exactly(reference, saved) -> None:
    """Sessions streamed 40 frames, their state turned by `saved(model, state)` into what an older
    step would have stored and brought back by `upgrade_state`, step on exactly as the state they left."""
    from models.interface import FrameBatch

    from .lti_reference import weights

    (root, rot), _ = reference
    model = load()
    w = weights(model.styles())
    state = model.init_state(root.shape[1])
    for t in range(40):
        _, state = model.step_batch(state, FrameBatch(root[t], rot[t]), w)
    resumed = model.upgrade_state(saved(model, state))
    for t in range(40, 60):
        a, state = model.step_batch(state, FrameBatch(root[t], rot[t]), w)
        b, resumed = model.step_batch(resumed, FrameBatch(root[t], rot[t]), w)
        assert np.array_equal(a.rotations, b.rotations) and np.array_equal(a.root, b.root)


def test_a_snapshot_from_before_the_packed_carry_resumes_exactly(reference):
    """A session's state saved before the carry was packed (every entry under its own key, flags
    as bools) is packed by `upgrade_state` and steps on exactly as the state it was saved from."""
    from .lti_reference import unpacked

    def saved(model, state):
        old = unpacked(state)
        assert "carry" not in old and old["feet_point"].dtype == np.int64
        return old

    _resumes_exactly(reference, saved)


def test_a_snapshot_saved_with_the_waving_arm_resumes_exactly(reference):
    """A state saved while the carry still held the waving arm's running means (before the feet)
    is brought to the current carry by `upgrade_state` and steps on as the state it was saved from;
    a current state comes back as it is."""
    from models.lti.kernels import FEET_AT
    from models.lti.model import WAVE_MEANS

    def saved(model, state):
        assert model.upgrade_state(state) is state
        means = np.random.default_rng(0).normal(size=(len(state["carry"]), WAVE_MEANS))
        return {**state, "carry": np.insert(state["carry"], [FEET_AT] * WAVE_MEANS, means, axis=1)}

    _resumes_exactly(reference, saved)


def test_a_large_batch_of_one_style_gives_the_same(reference, monkeypatch):
    """From `COMPACT_FROM` sessions of one style on, the step reads that style's state array as it
    is and hands the other styles one shared (read-only) zero state: the reference's first
    session (elderly) 20 times over gives its outputs 20 times, and the other styles rest at 0."""
    from . import lti_reference

    (root, rot), want = reference
    copies = 20
    monkeypatch.setattr(lti_reference, "MIXES", lti_reference.MIXES[:1] * copies)
    model = _recorded()
    got = stream(model, np.repeat(root[:, :1], copies, 1), np.repeat(rot[:, :1], copies, 1))
    for k in range(copies):
        np.testing.assert_allclose(got["rotations"][:, k], want["rotations"][:, 0], atol=1e-9)
        np.testing.assert_allclose(got["root"][:, k], want["root"][:, 0], atol=1e-8)
    from models.interface import FrameBatch

    w = lti_reference.weights(model.styles())
    _, state = model.step_batch(
        model.init_state(copies), FrameBatch(root[0, :1].repeat(copies, 0), rot[0, :1].repeat(copies, 0)), w
    )
    rest = [v for k, v in state.items() if k.startswith("x.") and k != "x.elderly"]
    assert state["x.elderly"].any() and not any(v.any() or v.flags.writeable for v in rest)


def test_packing_checks_each_field_against_its_schema():
    """The kernel rebuilds packed records by position (`kernels.unpack_constants`): a field of
    another kind or shape than its schema says is refused when packing, not misread."""
    from models.lti.kernels import pack

    f, i, b, index = pack([(np.ones((2, 3)), np.arange(4), True)], ["f2 i1 b0"])
    assert f.tolist() == [1.0] * 6 and i.tolist() == [0, 1, 2, 3] and b.tolist() == [True]
    assert index[:, :4].tolist() == [[0, 6, 2, 3], [0, 4, 4, 0], [0, 1, 0, 0]]
    for wrong in ("f1 i1 b0", "f2 f1 b0", "f2 i1"):
        with pytest.raises(ValueError):
            pack([(np.ones((2, 3)), np.arange(4), True)], [wrong])
