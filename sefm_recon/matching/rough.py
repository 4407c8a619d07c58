"""Rough matching (paper §4.2-4.3): intensity-jump key points along each line,
Fourier descriptors of their neighbourhood, and an ordered DP alignment.

The kernels live in :mod:`sefm_recon.matching.kernels`; this module is the
stage's public face, with array-in, array-out functions that tests and
notebooks can call on single sequences.
"""

from __future__ import annotations

import numpy as np

from . import kernels


def intensity_jumps(a: np.ndarray) -> np.ndarray:
    """``da_i = |a_{i-1} - a_{i+1}| / 2`` of a (n,) intensity sequence."""
    return kernels.intensity_jumps(np.ascontiguousarray(a, np.float32))


def detect_keypoints(a: np.ndarray, threshold: float) -> np.ndarray:
    """Indices of local maxima of the intensity jump above ``threshold``."""
    return kernels.detect_keypoints(np.ascontiguousarray(a, np.float32), float(threshold), 1)


def fft_descriptors(a: np.ndarray, keypoints: np.ndarray, radius: int = 8, ncoef: int = 6) -> np.ndarray:
    """(len(keypoints), 2 * ncoef * C) Fourier descriptors of the key points' windows.

    ``a`` is (n,) or (n, C); channels are described together (joint unit energy).
    """
    a2 = np.ascontiguousarray(a, np.float32)
    if a2.ndim == 1:
        a2 = a2[:, None]
    return kernels.fft_descriptors(a2, np.asarray(keypoints, np.int64), int(radius), int(ncoef))


def align_keypoints(p, q, desc1, desc2, max_dist: float, lo=None, hi=None) -> np.ndarray:
    """Ordered (LCS-like) DP alignment of key points ``p`` (line 1) and ``q`` (line 2).

    ``lo``/``hi`` bound the line-2 position of the partner of each line-1 sample
    (default: anywhere). Returns (k, 2) index pairs into ``p`` and ``q``.
    """
    p = np.asarray(p, np.int64)
    q = np.asarray(q, np.int64)
    n1 = int(p.max()) + 1 if len(p) else 1
    if lo is None:
        lo = np.zeros(n1, np.int64)
    if hi is None:
        hi = np.full(n1, np.iinfo(np.int64).max // 2, np.int64)
    return kernels.align_keypoints(
        p, q, np.ascontiguousarray(desc1, np.float32), np.ascontiguousarray(desc2, np.float32),
        np.asarray(lo, np.int64), np.asarray(hi, np.int64), float(max_dist),
    )
