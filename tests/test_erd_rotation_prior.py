"""Style-ERD's rotation prior (models/motion/style_carry.py, models/erd/rotation_prior.py): the input's head, hands
and twists are carried from the neutral style's real distribution to the target style's, the
output's rotations to the style's real ones, inside the style's real range, and nothing moves
when no style is asked for."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from models.interface import FrameBatch
from models.motion.rotations import quat_angle, quat_inv, quat_mul

from .clips import streamed_rotations, stylise_stream
from .reference import erd_carry
from .reference.erd_carry import carry_by_gait
from .reference.erd_carry import compiled_carry_slow as carry_slow
from .reference.style_carry import mixed_with

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO / "models" / "weights" / "erd"

pytestmark = pytest.mark.skipif(not (WEIGHTS / "leaf_prior.npz").exists(), reason="Style-ERD leaf prior not committed")


@pytest.fixture(scope="module")
def model():
    import models.erd

    return models.erd.load(WEIGHTS)


@pytest.fixture(scope="module")
def neutral(index):
    from models.data import load_motions, select

    clips = select(index, dataset="bandai-namco-2", split="val", style="normal")
    picked = [next(c for c in clips if c.content == k) for k in ("walk", "wave-both-hands", "raise-up-left-hand")]
    return [m.slice(0, 60) for m in load_motions(picked)]


def _apart(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternion distance blind to sign and to the data's last-digit norms (an angle from
    arccos is only good to ~1e-4 near zero)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.minimum(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


def _prior(model, which: str):
    """A committed prior's carry (`StyleCarry`) by name, `run_` or `stand_` before it: that gait's prior."""
    gait, _, name = which.partition("_") if which.startswith(("run_", "stand_")) else ("", "", which)
    stage = getattr(model.stages, name)
    return None if stage is None else getattr(stage, gait) if gait else stage.carry


def _onehot(model, style: str, scale: float = 1.0) -> np.ndarray:
    w = np.zeros(len(model.styles()))
    w[model.styles().index(style)] = scale
    return w


def test_log_and_exp_invert_each_other():
    from models.motion.rotations import quat_exp, quat_log

    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    assert np.all(quat_angle(quat_exp(quat_log(q)), q) < 1e-6)
    assert np.all(np.linalg.norm(quat_log(q), axis=-1) <= np.pi + 1e-9)


def _carry(model, which: str, rot: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The prior as the step applies it: the output prior reads the Hips without their heading."""
    from models.motion.bn_skeleton import HIPS

    prior = _prior(model, which)
    return prior(rot, w, hips=HIPS) if which == "output_prior" else prior(rot, w)


def _compared(which: str, rot: np.ndarray) -> np.ndarray:
    from models.motion.rotation_ball import comparable

    return comparable(rot) if which == "output_prior" else rot


@pytest.mark.parametrize("which", ["leaf_prior", "output_prior"])
def test_no_style_changes_nothing_and_a_style_stays_in_its_real_range(model, neutral, which):
    from models.motion.rotation_ball import split_heading

    prior = _prior(model, which)
    if prior is None:
        pytest.skip(f"no {which} committed")
    rot = np.concatenate([m.rotations for m in neutral])
    same = _carry(model, which, rot, np.zeros((len(rot), 6)))
    assert np.all(_apart(same, rot) < 1e-7)
    outside_before = 0
    for k, style in enumerate(model.styles()):
        w = np.repeat(_onehot(model, style)[None], len(rot), 0)
        moved = _carry(model, which, rot, w)
        # every joint inside the target style's real p98 angle from its mean (the clamp), where
        # the neutral input was not always
        dist = quat_angle(_compared(which, moved), prior.mean[k][None])
        assert np.all(dist <= prior.radius[k][None] + 1e-6), style
        outside_before += int(np.sum(quat_angle(_compared(which, rot), prior.mean[k][None]) > prior.radius[k][None]))
        # the root untouched; the hips too by the leaf prior, their heading by the output prior
        assert np.all(_apart(moved[:, 0], rot[:, 0]) < 1e-7)
        if which == "leaf_prior":
            assert np.all(_apart(moved[:, 1], rot[:, 1]) < 1e-7)
        else:
            assert np.all(_apart(split_heading(moved)[0], split_heading(rot)[0]) < 1e-7)
        # a small weight moves a little (the prior is continuous in the weights), and a mix of
        # two styles lies between them
        small = _carry(model, which, rot, 0.01 * w)
        assert np.max(quat_angle(small, rot)) < np.max(quat_angle(moved, rot)) * 0.05
        other = np.roll(w, 1, axis=1)
        half = _carry(model, which, rot, 0.5 * w + 0.5 * other)
        assert np.all(quat_angle(half, moved) <= quat_angle(_carry(model, which, rot, other), moved) + 1e-6)
    assert outside_before > 0


def test_a_batch_carries_each_row_as_alone(model, neutral):
    """Rows with different styles, mixes and no style in one batch: each as if alone, and as
    the numpy reference computes it."""
    prior = _prior(model, "output_prior") or _prior(model, "leaf_prior")
    rot = neutral[0].rotations[:5]
    w = np.zeros((5, 6))
    w[0, 1], w[1, 3], w[2, [0, 4]], w[3, 5] = 1.0, 1.5, 0.5, 1.0
    batch = prior(rot, w)
    for b in range(5):
        assert np.all(_apart(batch[b], prior(rot[b : b + 1], w[b : b + 1])[0]) < 1e-12)
    # the compiled step is the numpy reference, the Hips' heading removal included
    assert np.all(_apart(batch, erd_carry.apply(prior, rot, w)) < 1e-9)
    # and keeps each quaternion on its input's side (a stream's quaternions never flip sign),
    # plain styles (rows 0 and 3, taken without the blend's round trip) as well as the rest
    assert np.all(np.sum(batch * rot, axis=-1) > 0)
    if _prior(model, "output_prior") is not None:
        from models.motion.bn_skeleton import HIPS

        compiled = _prior(model, "output_prior")(rot, w, hips=HIPS)
        assert np.all(_apart(compiled, erd_carry.carry_output(_prior(model, "output_prior"), rot, w)) < 1e-9)


def test_streamed_head_and_hands_are_the_carried_input(model, neutral):
    """Without the output prior, the output's leaves are exactly the leaf prior's carried input
    (its slow part carried, the fast part on top: `slow_carry.py`; the decoder's own leaf
    rotations, which no position loss trained, are not used), and the twist source changes
    rotations, never where the joints are (the twist range, which turns the upper arms about
    themselves and so the forearms with them, and the hinge floor, which puts a forearm swung off
    its hinge back on it, are off here)."""
    from models.motion.skeleton import fk

    motion = neutral[1]
    w = _onehot(model, "feminine")
    leaves = [model.skeleton.index(n) for n in ("Head", "Hand_L", "Hand_R")]
    saved = model.stages

    def joints(o):
        tr = np.broadcast_to(model.skeleton.offsets, (1, model.skeleton.num_joints, 3)).copy()
        tr[:, 1] = o.root
        return fk(o.rotations, tr, model.skeleton.parents)[1][0]

    try:
        runs = {}
        for tag, off in (("bare", ("leaf_prior",)), ("leaf", ())):
            model.stages = saved.without("output_prior", "twist_range", "hinge_floor", *off)
            state, runs[tag] = model.init_state(1), []
            for t in range(30):
                frame = FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1])
                out, state = model.step_batch(state, frame, w[None])
                runs[tag].append(out)
    finally:
        model.stages = saved
    from models.erd.features import FPS
    from models.erd.gait import clip_gait

    leaf, clip = saved.leaf_prior, motion.slice(0, 30)
    share = clip_gait(model.maker.positions(clip.translations[:, 1], clip.rotations), FPS)
    source = erd_carry.clip_carry_slow(leaf.carry, leaf.run, clip.rotations, np.tile(w, (30, 1)), share, -1, leaf.stand)
    for t in range(30):
        src = source[t : t + 1]
        assert np.all(_apart(runs["leaf"][t].rotations[0, leaves], src[0, leaves]) < 1e-7)
        np.testing.assert_allclose(joints(runs["leaf"][t]), joints(runs["bare"][t]), atol=1e-6)


@pytest.mark.parametrize("which", ["leaf_prior", "output_prior"])
def test_committed_prior_is_well_formed(model, which):
    prior = _prior(model, which)
    if prior is None:
        pytest.skip(f"no {which} committed")
    S, J = len(model.styles()), model.skeleton.num_joints
    assert prior.source.shape == prior.mean.shape == (S, J, 4)
    assert prior.map.shape == (S, J, 3, 3) and prior.radius.shape == (S, J)
    np.testing.assert_allclose(np.linalg.norm(prior.mean, axis=-1), 1.0, atol=1e-9)
    # the maps are symmetric positive definite (optimal transport between Gaussians)
    np.testing.assert_allclose(prior.map, np.swapaxes(prior.map, -1, -2), atol=1e-9)
    assert np.all(np.linalg.eigvalsh(prior.map) > 0)
    # the styles' means really differ from the source somewhere (else the prior does nothing)
    shift = quat_angle(quat_mul(quat_inv(prior.source), prior.mean), np.array([0.0, 0, 0, 1]))
    assert np.degrees(shift.max()) > 2.0


@pytest.fixture(scope="module")
def run(index):
    from models.data import load_motions, select

    clip = select(index, dataset="bandai-namco-2", split="val", style="normal", content="run")[0]
    return load_motions([clip])[0].slice(0, 60)


def test_runs_take_the_run_priors_and_walks_do_not(model, run, neutral):
    """A running input is carried by the priors fitted on runs (`gait.py`); a walk never
    reaches the ramp, so its output is exactly what the all-content priors alone give."""
    from models.erd.features import FPS
    from models.erd.gait import clip_smoothed_speed, run_share

    if _prior(model, "run_output_prior") is None:
        pytest.skip("no run priors committed")

    def share_of(motion):
        speed = clip_smoothed_speed(model.maker.positions(motion.translations[:, 1], motion.rotations), FPS)
        return run_share(speed)

    assert share_of(run)[20:].min() == 1.0  # a run, once under way
    walk = neutral[0]
    assert share_of(walk).max() == 0.0
    w = _onehot(model, "feminine")
    saved = model.stages
    with_runs = {"run": streamed_rotations(model, run, w), "walk": streamed_rotations(model, walk, w)}
    try:
        walking = {k: replace(getattr(saved, k), run=None) for k in ("leaf_prior", "output_prior")}
        model.stages = saved.replace(**walking)
        without = {"run": streamed_rotations(model, run, w), "walk": streamed_rotations(model, walk, w)}
    finally:
        model.stages = saved
    np.testing.assert_array_equal(with_runs["walk"], without["walk"])
    moved = np.degrees(quat_angle(with_runs["run"][20:], without["run"][20:]))
    assert np.median(moved.max(axis=-1)) > 2.0  # the run priors do change a run


def test_the_gait_share_ramps_from_standing_through_walking_to_running():
    """-1 standing, 0 walking, 1 running, linear over each ramp; no speed yet counts as walking."""
    from models.erd.gait import RUN_RAMP_CM_S, STAND_RAMP_CM_S, UNMEASURED, gait_share

    (s0, s1), (r0, r1) = STAND_RAMP_CM_S, RUN_RAMP_CM_S
    speeds = np.array([UNMEASURED, 0.0, s0, (s0 + s1) / 2, s1, 100.0, r0, (r0 + r1) / 2, r1, 400.0])
    np.testing.assert_allclose(gait_share(speeds), [0, -1, -1, -0.5, 0, 0, 0, 0.5, 1, 1])


def test_a_stream_that_starts_mid_run_eases_into_the_run_priors(model, run):
    """A session's first frame has no speed yet and counts as walking; the gait share then moves
    toward the run priors by at most `GAIT_RATE` a frame (`gait.followed`) instead of turning the
    head by ~20 degrees between its first and second frame (toward feminine)."""
    from models.erd.features import FPS
    from models.erd.gait import GAIT_RATE, clip_gait

    if _prior(model, "run_output_prior") is None:
        pytest.skip("no run priors committed")
    head = model.skeleton.index("Head")
    out = streamed_rotations(model, run.slice(0, 30), _onehot(model, "feminine"))
    steps = np.degrees(quat_angle(out[:-1, head], out[1:, head]))
    assert steps.max() < 6.0, steps.round(1)
    share = clip_gait(model.maker.positions(run.translations[:, 1], run.rotations), FPS)
    np.testing.assert_allclose(share[:4], GAIT_RATE * np.arange(4))
    assert share[int(np.ceil(1 / GAIT_RATE)) + 5 :].min() == 1.0  # whole once under way


def test_a_runs_share_of_the_run_priors_does_not_swing_within_its_steps(model, run):
    """The Hips speed swings by +-40 cm/s within each running step; frame by frame it swung the
    share between the priors by ~0.5 a frame. Averaged over about a step (`gait.py`), it moves by
    at most 0.2 a frame once measured, and a stream steps it as the clip function computes it."""
    from models.erd.features import FPS
    from models.erd.gait import UNMEASURED, clip_hips_speed, clip_smoothed_speed, hips_speed, run_share, smoothed_speed

    pos = model.maker.positions(run.translations[:, 1], run.rotations)
    raw, smooth = run_share(clip_hips_speed(pos, FPS)), run_share(clip_smoothed_speed(pos, FPS))
    assert np.abs(np.diff(raw[1:60])).max() > 0.3  # what the steps do to the raw speed on this run
    assert np.abs(np.diff(smooth[1:60])).max() < 0.2
    average = np.array([UNMEASURED])
    for t in range(30):
        prev = pos[max(t - 1, 0)][None]
        average = smoothed_speed(average, hips_speed(pos[t][None], prev, np.array([t > 0]), FPS), np.array([t > 0]))
        assert average[0] == clip_smoothed_speed(pos, FPS)[t]


def test_run_frames_stay_inside_the_styles_whole_real_range(model, run):
    """The run priors carry toward the style's real runs, then clamp into the range the
    all-content prior keeps every frame in: no running row leaves it."""
    from models.motion.bn_skeleton import HIPS
    from models.motion.rotation_ball import comparable

    if _prior(model, "run_output_prior") is None:
        pytest.skip("no run priors committed")
    rot = run.rotations[:40]
    for k, style in enumerate(model.styles()):
        w = np.tile(_onehot(model, style), (len(rot), 1))
        out = carry_by_gait(
            _prior(model, "output_prior"), _prior(model, "run_output_prior"), rot, w, np.ones(len(rot)), hips=HIPS
        )
        bounds = _prior(model, "output_prior")
        angle = quat_angle(quat_mul(quat_inv(bounds.mean[k])[None], comparable(out)), np.array([0.0, 0, 0, 1]))
        assert np.all(angle <= bounds.radius[k][None] + 1e-6), style


def test_a_batch_of_runs_and_walks_steps_each_row_as_alone(model, run, neutral):
    """Rows running, walking, standing and between (a row's gait share is its own) in one
    batch give exactly what each gives alone."""
    w = np.stack([_onehot(model, s, k) for s, k in (("active", 1), ("feminine", 1), ("youthful", 0.5), ("elderly", 1))])
    motions = [run, neutral[0], run, neutral[2]]
    state = model.init_state(len(motions))
    alone = [model.init_state(1) for _ in motions]
    for t in range(30):
        frames = FrameBatch(
            np.stack([m.translations[t, 1] for m in motions]), np.stack([m.rotations[t] for m in motions])
        )
        out, state = model.step_batch(state, frames, w)
        for b, m in enumerate(motions):
            one, alone[b] = model.step_batch(
                alone[b], FrameBatch(m.translations[t : t + 1, 1], m.rotations[t : t + 1]), w[b : b + 1]
            )
            np.testing.assert_array_equal(out.rotations[b], one.rotations[0])


def test_the_gait_mix_compiled_is_its_numpy_reference(model, run):
    """`StyleCarry.mixed_with`: the all-content prior and the clamped run prior mixed by each
    row's share in one compiled pass, as the numpy reference computes it; share 0 is the
    all-content prior alone, exactly."""
    if _prior(model, "run_output_prior") is None:
        pytest.skip("no run priors committed")
    rot = run.rotations[:20]
    w = np.zeros((20, 6))
    w[:10, 2], w[10:, [1, 4]] = 1.0, 0.5  # plain rows and mixed rows
    share = np.tile([0.0, 0.3, 1.0, 0.7], 5)
    other, ran = _prior(model, "leaf_prior"), _prior(model, "run_leaf_prior")
    compiled = other.mixed_with(ran, other.bounds, rot, w, share)
    assert np.all(_apart(compiled, mixed_with(other, ran, other.bounds, rot, w, share)) < 1e-9)
    walking = share == 0.0
    np.testing.assert_array_equal(compiled[walking], other(rot[walking], w[walking]))


def test_a_held_pose_is_carried_as_the_prior_carries_it(model, neutral):
    """Slow part = the pose itself: the output prior's carry, unchanged by `slow_carry`."""
    from models.motion.bn_skeleton import HIPS

    q = neutral[0].rotations[:8]
    w = np.tile(_onehot(model, "feminine"), (len(q), 1))
    share = np.zeros(len(q))
    slowly, slow = carry_slow(_prior(model, "output_prior"), None, q, q, w, share, hips=HIPS)
    assert np.all(_apart(slow, q) < 1e-12)
    assert np.all(_apart(slowly, carry_by_gait(_prior(model, "output_prior"), None, q, w, share, hips=HIPS)) < 1e-9)


def test_the_priors_never_magnify_a_one_frame_flick(model, neutral):
    """A held pose whose head flicks 8 degrees for one frame: carried whole, the flick grows by
    the prior's gain g toward the style whose head gain is largest (above 1); carried slowly,
    only the slow copy's share of it (SLOW_WEIGHT) is carried with the gain, the rest passes at
    most as it came: about SLOW_WEIGHT g + (1 - SLOW_WEIGHT) times the flick instead of g times."""
    from models.erd.slow_carry import SLOW_WEIGHT
    from models.motion.bn_skeleton import HIPS
    from models.motion.rotations import quat_exp

    FLICK = 8.0  # degrees, times the gain still inside the style's head range (no clamp in the way)
    head = model.skeleton.index("Head")
    prior = _prior(model, "output_prior")
    all_gains, all_axes = np.linalg.eigh(prior.map[:, head])
    style = int(np.argmax(all_gains[:, -1]))
    gains, axes, w = all_gains[style], all_axes[style], _onehot(model, model.styles()[style])[None]
    assert gains[-1] > 1.2
    pose = neutral[0].rotations[:1]
    flicked = pose.copy()  # about the axis the map stretches most
    flicked[:, head] = quat_mul(pose[:, head], quat_exp(np.radians(FLICK) * axes[:, -1]))
    frames = [pose] * 10 + [flicked] + [pose] * 3
    slow, whole, slowly = np.zeros_like(pose), [], []
    for q in frames:
        whole.append(carry_by_gait(prior, None, q, w, np.zeros(1), hips=HIPS)[0, head])
        out, slow = carry_slow(prior, None, q, slow, w, np.zeros(1), hips=HIPS)
        slowly.append(out[0, head])
    jump = lambda out: np.degrees(quat_angle(out[9], out[10]))  # noqa: E731
    assert jump(whole) > 1.2 * FLICK
    # within a degree: rotations compose, they do not add
    assert jump(slowly) <= SLOW_WEIGHT * jump(whole) + (1.0 - SLOW_WEIGHT) * FLICK + 1.0, (jump(whole), jump(slowly))


@pytest.mark.parametrize("mix", ["one style", "a mix at part intensity"])
def test_compiled_slow_carry_is_the_numpy_reference(model, neutral, mix):
    """`carry_slow` (one compiled pass) against its numpy reference (follow, `carry_by_gait`, the
    fast part and the clamp, each in numpy), both stages, with the run and stand priors part-shared."""
    from models.motion.bn_skeleton import HIPS

    rng = np.random.default_rng(3)
    q = np.concatenate([m.rotations[:20] for m in neutral])
    B = len(q)
    w = np.tile(_onehot(model, "elderly"), (B, 1)) if mix == "one style" else rng.dirichlet(np.ones(6), B) * 0.8
    share = rng.choice([-1.0, -0.6, 0.0, 0.4, 1.0], B)
    slow = np.roll(q, 1, axis=0) + 0.05 * rng.normal(size=q.shape)
    slow[::7] = 0.0  # unset rows start at q
    for name, hips in (("leaf_prior", -1), ("output_prior", HIPS)):
        other, run, stand = (_prior(model, f"{g}{name}") for g in ("", "run_", "stand_"))
        got, got_slow = carry_slow(other, run, q, slow, w, share, hips, stand)
        want, want_slow = erd_carry.carry_slow(other, run, q, slow, w, share, hips, stand)
        assert np.all(_apart(got_slow, want_slow) < 1e-12)
        assert np.all(_apart(got, want) < 1e-9)


def test_a_raise_up_streamed_equals_the_whole_clip(model, neutral):
    """The whole-clip path (`models/erd/offline.py`: the torch network over the clip, then the
    stages, `tests/reference/erd_offline.py`) carries a raise-up as the stream does."""
    from .reference.erd_offline import stylise

    motion, w = neutral[2], _onehot(model, "elderly")
    whole = stylise(model.torch_generator(), model, motion, w)
    np.testing.assert_allclose(stylise_stream(model, motion, w).rotations, whole.rotations, atol=2e-4)


def test_the_arms_twist_inside_the_styles_real_interval(model, neutral):
    """`twist_range.py`: streamed toward a style, every arm joint's twist about its bone (against
    the style's real mean) lies in the style's real TRAIN p1..p99 interval; with no style weight
    the step is exactly as without the range."""
    import copy

    from models.motion.rotations import twist_angle

    ranges = model.stages.twist_range
    assert ranges is not None
    without = copy.copy(model)
    without.stages = model.stages.without("twist_range")
    for style in ("masculine", "youthful"):
        k = model.styles().index(style)
        arms = np.concatenate([streamed_rotations(model, m, _onehot(model, style)) for m in neutral])[:, ranges.joints]
        t = twist_angle(quat_mul(quat_inv(ranges.mean[k])[None], arms), ranges.axes)
        assert np.all(t >= ranges.lo[k] - 1e-9) and np.all(t <= ranges.hi[k] + 1e-9), style
    none = np.zeros(len(model.styles()))
    np.testing.assert_array_equal(
        streamed_rotations(model, neutral[0], none), streamed_rotations(without, neutral[0], none)
    )


def test_the_compiled_twist_range_is_its_numpy_reference(model):
    rng = np.random.default_rng(5)
    q = rng.normal(size=(40, model.skeleton.num_joints, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    w = np.zeros((40, len(model.styles())))
    w[:20, 4] = 1.0  # one style
    w[20:30, 1], w[20:30, 3] = 0.6, 0.3  # a mix below full weight; the last 10 rows: no style
    ranges = model.stages.twist_range
    got, want = erd_carry.twist_stage(ranges, q, w), erd_carry.twist_clamp(ranges, q, w)
    assert _apart(got, want).max() < 1e-9


def _frames(v: np.ndarray) -> np.ndarray:
    """(N, 2, 4): joint 0 the identity, joint 1 the rotations of rotation vectors `v` (N, 3)."""
    from models.motion.rotations import quat_exp

    q = np.zeros((len(v), 2, 4))
    q[:, 0, 3] = 1.0
    q[:, 1] = quat_exp(v)
    return q


def _ring(n: int, radius: float = 0.3, turn: float = 2 * np.pi) -> np.ndarray:
    """(n, 3) rotation vectors on an arc (`turn` radians) of a ring about the identity."""
    t = np.linspace(0.0, turn, n, endpoint=False)
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.zeros(n)], axis=1)


def test_the_output_prior_takes_the_carry_that_brings_frames_nearest_the_real_ones():
    from models.erd.rotation_prior import chosen, mean_shift, near_percentile, output_carry
    from models.motion.style_carry import StyleCarry

    rng = np.random.default_rng(0)
    line = np.zeros((400, 3))
    line[:, 0] = np.linspace(-0.3, 0.3, 400)
    # real frames: a ring and a cross through its centre, supports no Gaussian fills
    real = _frames(np.concatenate([_ring(720), line, line[:, [1, 0, 2]]]))
    # half the ring: on the real frames though its Gaussian is not theirs (the map's stretch
    # moves them off): only clamped
    half = _ring(500, turn=np.pi)
    # one bar of the cross, a little noise across it, turned aside: the mean's shift brings it
    # back, the map would stretch the noise across the gap
    bar = line + [0.0, 0.0, 0.15] + rng.normal(0.0, [0.0, 0.005, 0.0], (400, 3))
    # the ring shrunk about a shifted centre: only the whole carry brings it back
    small = _ring(500, 0.15) + [0.1, 0.0, 0.0]
    produced = [_frames(v) for v in (half, bar, small)]
    fitted = output_carry(produced, [real] * 3, ())
    carry = StyleCarry.fit(produced, [real] * 3, (0,))
    kinds = (carry, mean_shift(carry), carry.bounds)
    far = [near_percentile(k, produced, [real] * 3)[:, 1] for k in kinds]
    assert np.argmin(far, axis=0).tolist() == [2, 1, 0]
    np.testing.assert_array_equal(fitted.map[0, 1], np.eye(3))  # only clamped
    np.testing.assert_allclose(fitted.source[0, 1], fitted.mean[0, 1])
    np.testing.assert_array_equal(fitted.map[1, 1], np.eye(3))  # shifted, not stretched
    np.testing.assert_allclose(fitted.source[1, 1], carry.source[1, 1])
    np.testing.assert_allclose(fitted.map[2, 1], carry.map[2, 1])  # the whole carry
    np.testing.assert_allclose(fitted.radius, carry.radius)
    # `chosen` takes each entry from its own kind
    mixed = chosen(kinds, np.array([[0, 2], [1, 0], [2, 1]]))
    np.testing.assert_allclose(mixed.source[0, 1], carry.mean[0, 1])
    np.testing.assert_allclose(mixed.map[1, 1], carry.map[1, 1])
    np.testing.assert_allclose(mixed.map[2, 1], np.eye(3))


def test_a_partial_carry_goes_its_share_of_the_way_inside_the_same_range():
    from models.erd.rotation_prior import partial
    from models.motion.style_carry import StyleCarry

    real, produced = _frames(_ring(720)), _frames(0.5 * _ring(500) + [0.1, 0.05, 0.0])
    carry = StyleCarry.fit([produced], [real], (0,))
    assert partial(carry, 1.0) is carry
    half = partial(carry, 0.5)
    np.testing.assert_allclose(half.map, 0.5 * (np.eye(3) + carry.map))
    np.testing.assert_array_equal(half.mean, carry.mean)  # the clamp holds the style's own range
    np.testing.assert_array_equal(half.radius, carry.radius)
    np.testing.assert_array_equal(half.source[:, 0], carry.source[:, 0])  # joint_Root: nothing to carry
    np.testing.assert_array_equal(half.map[:, 0], carry.map[:, 0])
    # the network's mean lands half way to the style's
    src = carry.source[:, None, :, :][0]
    w = np.ones((1, 1))
    whole, halfway = carry(src, w)[0, 1], half(src, w)[0, 1]
    np.testing.assert_allclose(quat_angle(src[0, 1], halfway), 0.5 * quat_angle(src[0, 1], whole), rtol=1e-6)
    np.testing.assert_allclose(quat_angle(whole, halfway), 0.5 * quat_angle(src[0, 1], whole), rtol=1e-6)


def test_one_raised_hand_leaves_the_other_arm_where_the_style_holds_it(model, index):
    """The priors weigh every content alike in what they map from and to (`content_balanced`): a
    style's real clips mix contents otherwise than the fit's inputs do, and a pooled mean read that
    mix as style, swinging masculine's hanging right arm away from every real frame of the style
    whenever the left hand went up."""
    from models.data import load_motions, select

    arm, raised = model.skeleton.index("UpperArm_R"), "raise-up-left-hand"
    real = select(index, dataset="bandai-namco-2", split="train", style="masculine", content=raised)
    held = np.concatenate([m.rotations[:, arm] for m in load_motions(real)])
    clips = select(index, dataset="bandai-namco-2", split="val", style="normal", content=raised)
    for clip, motion in zip(clips, load_motions(clips)):
        out = streamed_rotations(model, motion.slice(0, 60), _onehot(model, "masculine"))[:, arm]
        nearest = np.degrees(quat_angle(out[:, None], held[None]).min(axis=1))
        assert np.percentile(nearest, 90) < 7.5, clip.name


def test_the_ankles_stay_near_the_styles_real_ankles(model, neutral, index):
    """The output prior carries the ankles like the arms (the other leg joints it only clamps: the
    planter bends them): the network swings youthful's ankles several times the real spread, and
    clamped alone one foot stood 23 degrees from any real youthful frame of the same content."""
    from models.data import load_motions, select

    feet = [model.skeleton.index(n) for n in ("Foot_L", "Foot_R")]
    out = streamed_rotations(model, neutral[2], _onehot(model, "youthful"))[:, feet]
    real = load_motions(
        select(index, dataset="bandai-namco-2", split="train", style="youthful", content="raise-up-left-hand")
    )
    held = np.concatenate([m.rotations[:, feet] for m in real])
    for k in range(len(feet)):
        nearest = np.degrees(quat_angle(out[:, None, k], held[None, :, k]).min(axis=1))
        assert np.percentile(nearest, 90) < 15.0


def test_standing_frames_take_the_stand_prior_and_keep_the_style_standing(model, index):
    """Fitted on the whole of a style, the output prior read a standing pose as a walk's: while
    the hands went up, youthful's right foot turned 8-11 degrees (p90) from every real standing
    youthful frame and elderly's hanging left forearm 13-16 degrees. A frame whose input stands
    (`gait.stand_share`) takes the priors fitted on standing clips (`gait_split`), which keep both
    where the style's real standing frames are."""
    from models.data import load_motions, select
    from models.erd.features import FPS
    from models.erd.gait import clip_smoothed_speed, stand_share

    if _prior(model, "stand_output_prior") is None:
        pytest.skip("no stand prior committed")
    for style, joint, content, most in (
        ("youthful", "Foot_R", "raise-up-both-hands", 6.0),
        ("elderly", "LowerArm_L", "raise-up-right-hand", 10.0),
    ):
        j = model.skeleton.index(joint)
        real = select(index, dataset="bandai-namco-2", split="train", style=style)
        real = [c for c in real if c.content.startswith(("raise", "wave"))]
        held = np.concatenate([m.rotations[::2, j] for m in load_motions(real)])
        clips = select(index, dataset="bandai-namco-2", split="val", style="normal", content=content)
        for clip, motion in zip(clips, load_motions(clips)):
            motion = motion.slice(0, 90)
            speed = clip_smoothed_speed(model.maker.positions(motion.translations[:, 1], motion.rotations), FPS)
            assert stand_share(speed)[1:].min() == 1.0, clip.name  # it stands throughout
            out = streamed_rotations(model, motion, _onehot(model, style))[:, j]
            nearest = np.degrees(quat_angle(out[:, None], held[None]).min(axis=1))
            assert np.percentile(nearest, 90) < most, (style, clip.name)
