"""LPN-FiLM (Mason, Starke & Komura 2022): real-time style modelling with local motion phases.

First increment: local motion phases (`phases`), their Figure-4 style plot (`plots`,
`python -m models.lpn phases-plot`)."""

from .phases import (BONES, LocalPhases, SinusoidFit, circular_mean, contact_free_source, contact_source,
                     fit_sinusoid, local_phases, lowpass, phase_features, principal_axis, sliding_normalise,
                     step_frequency, style_axes, touchdowns)

__all__ = ["BONES", "LocalPhases", "SinusoidFit", "circular_mean", "contact_free_source", "contact_source",
           "fit_sinusoid", "local_phases", "lowpass", "phase_features", "principal_axis", "sliding_normalise",
           "step_frequency", "style_axes", "touchdowns"]
