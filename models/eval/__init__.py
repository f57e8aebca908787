"""Evaluation suite scoring every streaming method on the same held-out clips.

Independent judges trained on real data only (never on any method's output):
  - a style classifier and a content classifier (1-D temporal convs over ~1 s windows),
  - a denoising autoencoder over 24-frame windows whose latent feeds the FMD.
Metrics on stylised test-split `normal` clips: target-style recognition, content kept, FMD to the
real target style, foot-skating ratio, root-path deviation from the input.

    .venv/bin/python -m models.eval            # full run -> docs/evaluation.md, docs/eval/
    .venv/bin/python -m models.eval --quick    # tiny subset, seconds
    .venv/bin/python -m models.eval.train      # re-train the judges -> models/weights/eval/
"""

from .features import FEATURE_DIM, clip_features
from .judges import Judges, load_judges

__all__ = ["FEATURE_DIM", "clip_features", "Judges", "load_judges"]
