"""LTI's rotation prior: every joint's output rotation stays inside the ball that real data of the
output style fills around that joint's mean rotation.

Why: a per-joint LTI system is linear in the exponential map, so a raised arm or a deep knee bend
that lies near the edge of the training data can be carried past anything the style shows (an
elbow bent 15 degrees further than any real elderly take). The ball, its tanh saturation and the
heading-free Hips are shared with LPN-FiLM and live in `models.motion.rotation_ball`; the
streaming step clamps each style's rotations with `rotation_ball_kernels.clamp_joint` before the
styles are blended (`kernels.py`). Radii: quantiles of the output style's TRAIN clips, all
contents (`train.style_prior`).
"""

from __future__ import annotations

from ..motion.rotation_ball import NO_PRIOR, clamp_rotations, comparable, fit_prior, mean_rotation, saturate, up_twist

__all__ = ["NO_PRIOR", "clamp_rotations", "comparable", "fit_prior", "mean_rotation", "saturate", "up_twist"]
