"""Dense matching (paper §4.4): between consecutive rough matches, resample both
segments to equal length and align every sample by DP with the
sampling-insensitive cost ``C = max(0, I(y) - I_max, I_min - I(y))``.
"""

from __future__ import annotations

import numpy as np

from . import kernels


def _as2d(x):
    x = np.ascontiguousarray(x, np.float32)
    return x[:, None] if x.ndim == 1 else x


def resample(seq: np.ndarray, length: int) -> np.ndarray:
    """Linear interpolation of a (n,) or (n, C) sequence to ``length`` samples."""
    s = _as2d(seq)
    out = kernels.resample(s, 0, len(s) - 1, int(length))
    return out[:, 0] if np.ndim(seq) == 1 else out


def align_segment(x: np.ndarray, y: np.ndarray, penalty: float = 20.0, band: int | None = None):
    """Align equal-length sequences x, y ((L,) or (L, C)); see :func:`kernels.align_segment`.

    Returns ``(v_of_u, run, cost)``: partner position in y of each sample of x,
    length of the one-to-many run it belongs to, and the matching cost.
    """
    x2, y2 = _as2d(x), _as2d(y)
    if x2.shape != y2.shape:
        raise ValueError(f"sequences must have equal shapes, got {x2.shape} and {y2.shape}")
    if band is None:
        band = len(x2)
    return kernels.align_segment(x2, y2, float(penalty), int(band))
