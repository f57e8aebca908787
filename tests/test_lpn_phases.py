"""Local motion phases (models.lpn.phases): the sinusoid fit on synthetic data, then on real walks."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motion, select
from models.lpn.phases import (
    BONES,
    fit_sinusoid,
    local_phases,
    phase_features,
    principal_axis,
    style_axes,
)

FPS = 30.0


def step_frequency(contact: np.ndarray, fps: float) -> float:
    """Cycle frequency (Hz) of one foot from its touchdowns: (n - 1) cycles between the first and
    last. NaN with fewer than two."""
    c = np.asarray(contact, dtype=bool)
    t = np.flatnonzero(~c[:-1] & c[1:]) + 1
    if len(t) < 2:
        return float("nan")
    return (len(t) - 1) * fps / float(t[-1] - t[0])


def circular_mean(angles: np.ndarray) -> float:
    """Mean direction of angles (radians), in (-pi, pi]."""
    return float(np.angle(np.exp(1j * np.asarray(angles)).mean()))


def test_fit_recovers_synthetic_sinusoid():
    t = np.arange(240) / FPS
    f, s, a, b = 1.37, 0.9, 0.7, 0.25
    fit = fit_sinusoid(a * np.sin(2 * np.pi * f * t - s) + b, FPS)
    assert np.abs(fit.frequency - f).max() < 2e-3
    assert np.abs(np.angle(np.exp(1j * (fit.phase - (2 * np.pi * f * t - s))))).max() < 5e-3
    assert np.abs(fit.amplitude - a).max() < 2e-3
    assert np.abs(fit.offset - b).max() < 2e-3
    assert np.abs(fit.value() - (a * np.sin(2 * np.pi * f * t - s) + b)).max() < 5e-3


def test_fit_tracks_a_frequency_change():
    """Per-frame fit: a step from 0.8 Hz to 1.6 Hz is followed once the window has passed it."""
    t = np.arange(300) / FPS
    freq = np.where(t < 5, 0.8, 1.6)
    x = np.sin(2 * np.pi * np.cumsum(freq) / FPS)
    fit = fit_sinusoid(x, FPS)
    assert np.abs(fit.frequency[30:120] - 0.8).max() < 0.02
    assert np.abs(fit.frequency[180:270] - 1.6).max() < 0.02


def test_phase_features_norm_is_amplitude():
    rng = np.random.default_rng(0)
    phase, amp = rng.uniform(0, 2 * np.pi, (50, 4)), rng.uniform(0, 3, (50, 4))
    feat = phase_features(phase, amp)
    assert feat.shape == (50, 4, 2)
    np.testing.assert_allclose(np.linalg.norm(feat, axis=-1), amp, atol=1e-12)
    np.testing.assert_allclose(np.arctan2(feat[..., 0], feat[..., 1]) % (2 * np.pi), phase, atol=1e-9)


def test_principal_axis_points_forward():
    t = np.linspace(0, 4 * np.pi, 200)
    pts = np.stack([0.1 * np.sin(t), 1.0 + 0.05 * np.cos(t), -0.4 * np.sin(t)], axis=1)  # swing along -Z
    centre, axis = principal_axis(pts)
    np.testing.assert_allclose(centre, [0, 1, 0], atol=1e-2)
    assert axis[2] > 0.9


@pytest.fixture(scope="module")
def walks():
    index = build_index(["bandai-namco-2"])
    clips = select(index, style="normal", content="walk", split="train")[:3]
    return [load_motion(c) for c in clips]


@pytest.fixture(scope="module")
def phases(walks):
    return [local_phases(m) for m in walks]


def test_shapes_and_amplitude_scaling(phases):
    lp = phases[0]
    F = lp.phase.shape[0]
    assert lp.bones == BONES
    assert lp.features.shape == (F, 4, 2)
    assert lp.frequency.shape == lp.amplitude.shape == (F, 4)
    assert np.all((lp.phase >= 0) & (lp.phase < 2 * np.pi))
    np.testing.assert_allclose(np.linalg.norm(lp.features, axis=-1), lp.amplitude, atol=1e-9)
    assert np.all(lp.amplitude[30:-30] > 0.2)  # every limb moves in a walk


def test_foot_frequency_matches_contact_steps(phases):
    for lp in phases:
        for side, col in ((0, BONES.index("Foot_L")), (1, BONES.index("Foot_R"))):
            steps = step_frequency(lp.contacts[:, side], lp.fps)
            fitted = float(np.median(lp.frequency[:, col]))
            assert abs(fitted / steps - 1) < 0.15, (steps, fitted)


def test_left_right_half_a_cycle_apart(phases):
    for lp in phases:
        feet = circular_mean(lp.phase[:, BONES.index("Foot_L")] - lp.phase[:, BONES.index("Foot_R")])
        hands = circular_mean(lp.phase[:, BONES.index("Hand_L")] - lp.phase[:, BONES.index("Hand_R")])
        assert abs(abs(feet) - np.pi) < 0.4, feet
        assert abs(abs(hands) - np.pi) < 0.5, hands


def test_phase_advances_once_per_step(phases):
    """Unwrapped foot phase grows by 2pi per contact cycle, never runs backwards for long."""
    for lp in phases:
        col = BONES.index("Foot_L")
        unwrapped = np.unwrap(lp.phase[:, col])
        cycles = (unwrapped[-30] - unwrapped[30]) / (2 * np.pi)
        expected = step_frequency(lp.contacts[:, 0], lp.fps) * (lp.phase.shape[0] - 60) / lp.fps
        assert abs(cycles - expected) < 0.5
        assert np.mean(np.diff(unwrapped[30:-30]) > 0) > 0.95


def test_style_centring_matches_per_clip(walks):
    """Per-style-and-gait centring gives the same rhythm as per-clip centring."""
    axes = style_axes(walks)
    assert set(axes) == {"Hand_L", "Hand_R"}
    a, b = local_phases(walks[0], axes=axes), local_phases(walks[0])
    d = circular_mean(a.phase[:, 0] - b.phase[:, 0])
    assert abs(d) < 0.3
