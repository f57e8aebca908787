"""The sealed evaluation of every streaming method (`sealed.py`), and what it is built from.

Judges trained on real data only (never on any method's output):
  - the style judge (`style_judge.py`): window statistics and a linear read, both Bandai Namco
    datasets, refit by `python -m models.eval.fit_style_judge`;
  - the conv-net content judge (`judges.py`, refit by `python -m models.eval.train`).
Physical metrics no clamp or lock in a model enforces (`physical.py`), inputs from every source
(`sources.py`), running sessions (`history.py`), 95 % intervals (`intervals.py`).

    make eval                                  # validation inputs -> out/eval-val/
    make eval-final                            # sealed test inputs -> docs/evaluation.md, once a change is finished
    .venv/bin/python -m models.eval --quick    # two clips a source, seconds
"""

from .features import FEATURE_DIM, clip_features
from .judges import Judges, load_judges

__all__ = ["FEATURE_DIM", "clip_features", "Judges", "load_judges"]
