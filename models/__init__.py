"""The three style-transfer methods (LTI, Style-ERD, LPN-FiLM) and their shared motion maths."""

from . import numba_cache  # noqa: F401  (before any kernel module: keys numba's on-disk cache)
