"""The sealed evaluation of every streaming method (`sealed.py`), and what it is built from:
judges trained on real data only (`style_judge.py`, `judges.py`), physical metrics no model clamp
enforces (`physical.py`), inputs from every source (`sources.py`), running sessions
(`history.py`) and 95 % intervals (`intervals.py`).

    make eval                                  # validation inputs -> out/eval-val/
    make eval-final                            # sealed test inputs -> docs/evaluation.md, once a change is finished
    .venv/bin/python -m models.eval --quick    # two clips a source, seconds
"""

from .features import FEATURE_DIM, clip_features
from .judges import Judges, load_judges

__all__ = ["FEATURE_DIM", "clip_features", "Judges", "load_judges"]
