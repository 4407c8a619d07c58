"""Rough matching (paper §4.2-4.3): intensity-jump key points along each line,
Fourier descriptors of their neighbourhood, and an ordered DP alignment.

:func:`match_keypoints` does all three on one line pair inside the line kernel
(:func:`.dense.match_lines`); the array-in, array-out functions below it are
the same steps on single sequences, for tests and notebooks.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit


class RoughOptions(NamedTuple):
    """Settings of :func:`match_keypoints`."""

    threshold: float  #: intensity jump ``da_i`` (0-255) above which a sample is a key point
    radius: int  #: half width of the descriptor window, samples
    ncoef: int  #: Fourier coefficients of the descriptor (beyond DC)
    max_dist: float  #: descriptors farther apart than this never match


class RoughMatches(NamedTuple):
    """Key points of a line pair and their ordered rough matches (:func:`match_keypoints`)."""

    kp1: np.ndarray  #: (m,) int64 key points on line 1, increasing sample indices
    kp2: np.ndarray  #: (n,) int64 on line 2
    pairs: np.ndarray  #: (k, 2) int64 matched indices into ``kp1`` and ``kp2``, increasing
    jump1: np.ndarray  #: (m,) float32 intensity jump at each key point of line 1 (empty without pairs)
    jump2: np.ndarray  #: (n,) float32 the same on line 2


@njit(cache=True)
def _intensity_jumps(a: np.ndarray) -> np.ndarray:
    """``da_i = |a_{i-1} - a_{i+1}| / 2`` (paper §4.3), 0 at both ends. ``a``: (n,) float32."""
    n = a.shape[0]
    da = np.zeros(n, np.float32)
    for i in range(1, n - 1):
        da[i] = abs(a[i - 1] - a[i + 1]) * 0.5
    return da


@njit(cache=True)
def _detect_keypoints(a: np.ndarray, threshold: float, border: int) -> np.ndarray:
    """Positions where the intensity jump exceeds ``threshold`` and is a local maximum.

    Non-maximum suppression keeps one key point per edge, where the paper's plain
    threshold would mark every sample of a blurred edge. ``border`` samples at
    both ends are skipped (their neighbourhoods are incomplete).
    """
    da = _intensity_jumps(a)
    n = a.shape[0]
    out = np.empty(n, np.int64)
    k = 0
    for i in range(max(border, 1), n - max(border, 1)):
        if da[i] > threshold and da[i] >= da[i - 1] and da[i] > da[i + 1]:
            out[k] = i
            k += 1
    return out[:k]


@njit(cache=True)
def _fft_descriptors(a: np.ndarray, keypoints: np.ndarray, radius: int, ncoef: int) -> np.ndarray:
    """Fourier descriptors of the neighbourhood of each key point (paper §4.3).

    The window ``a[i - radius : i + radius + 1]`` of every channel is
    Hann-tapered, made zero-mean, and described by the real and imaginary parts
    of its DFT coefficients 1..ncoef (the DC term is gone with the mean). The
    descriptor is normalised to unit energy over all channels, so a gain or
    offset between the photos does not matter. The window is centred on the key
    point, so the phase says on which side the edge rises. With neighbouring
    lines as channels, the descriptor sees a small 2-D patch.

    Args:
        a: (n, C) float32 samples.
    Returns:
        (len(keypoints), 2 * ncoef * C) float32.
    """
    n = a.shape[0]
    C = a.shape[1]
    size = 2 * radius + 1
    m = keypoints.shape[0]
    D = 2 * ncoef
    out = np.zeros((m, D * C), np.float32)
    win = np.empty(size, np.float64)
    taper = np.empty(size, np.float64)
    for s in range(size):
        taper[s] = 0.5 - 0.5 * np.cos(2.0 * np.pi * (s + 1) / (size + 1))
    cos_t = np.empty((ncoef, size), np.float64)
    sin_t = np.empty((ncoef, size), np.float64)
    for c in range(ncoef):
        for s in range(size):
            ang = 2.0 * np.pi * (c + 1) * s / size
            cos_t[c, s] = np.cos(ang)
            sin_t[c, s] = np.sin(ang)
    for k in range(m):
        i0 = keypoints[k] - radius
        energy = 0.0
        for ch in range(C):
            mean = 0.0
            for s in range(size):
                idx = min(max(i0 + s, 0), n - 1)
                win[s] = a[idx, ch]
                mean += win[s]
            mean /= size
            for s in range(size):
                win[s] = (win[s] - mean) * taper[s]
            for c in range(ncoef):
                re = 0.0
                im = 0.0
                for s in range(size):
                    re += win[s] * cos_t[c, s]
                    im -= win[s] * sin_t[c, s]
                out[k, ch * D + 2 * c] = re
                out[k, ch * D + 2 * c + 1] = im
                energy += re * re + im * im
        scale = 1.0 / np.sqrt(energy + 1e-3)
        for c in range(D * C):
            out[k, c] *= scale
    return out


@njit(cache=True)
def _align_keypoints(p, q, desc1, desc2, lo, hi, max_dist):
    """Ordered alignment of two key point sequences by DP (LCS-like, paper §4.2).

    Maximises the summed similarity ``max_dist - |d1 - d2|`` over strictly
    increasing pairs; a key point may stay unmatched at no cost (seen in one
    view only). A pair is allowed only when ``q[j]`` lies in the search band
    ``[lo[p[i]], hi[p[i]]]`` of line-2 positions.

    The DP table ``S[i, j]`` (best score of ``p[:i]`` against ``q[:j]``) is
    kept as one row, updated in place: outside the band a row only repeats
    the row above until its first in-band cell, and after the last one only
    until the row above catches up, so a narrow band costs a few cells per
    key point instead of a full row. Each cell
    also keeps the last pair of its optimal path (``owner``), so the pairs
    are read back without the full table. Ties are broken as in the full
    table: the row above, then the cell to the left, then the pair.

    Args:
        p, q: (m,), (n,) increasing key point positions on line 1 and line 2.
        desc1, desc2: (m, D), (n, D) descriptors.
        lo, hi: (len(line 1),) band of line-2 positions for every line-1 sample.
    Returns:
        (k, 2) int64 indices into ``p`` and ``q`` of the matched pairs, increasing.
    """
    m = p.shape[0]
    n = q.shape[0]
    D = desc1.shape[1]
    max_d2 = max_dist * max_dist
    # In-band columns of every row: q[j0[i] : j1[i]].
    j0 = np.searchsorted(q, lo[p], "left")
    j1 = np.searchsorted(q, hi[p], "right")
    total = 0
    for i in range(m):
        total += max(0, j1[i] - j0[i])
    pair_i = np.empty(total, np.int64)
    pair_j = np.empty(total, np.int64)
    pred = np.empty(total, np.int64)
    S = np.zeros(n + 1, np.float32)  # S[j]: column j of the current row (0: no key point of q)
    owner = np.full(n + 1, -1, np.int64)
    k = 0
    for i in range(m):
        a = j0[i]
        b = j1[i]
        if b <= a:
            continue
        # Row i-1's values at columns a .. b (cell j + 1 is q[:j + 1]).
        diag_s = S[a]
        diag_o = owner[a]
        left_s = S[a]
        left_o = owner[a]
        for j in range(a, b):
            up_s = S[j + 1]
            up_o = owner[j + 1]
            best = up_s
            bo = up_o
            if left_s > best:
                best = left_s
                bo = left_o
            # Squared distance, abandoned once past max_dist: most pairs in
            # the band are far apart, and the descriptors are long.
            d2 = 0.0
            for c in range(D):
                diff = desc1[i, c] - desc2[j, c]
                d2 += diff * diff
                if d2 >= max_d2:
                    break
            if d2 < max_d2:
                cand = diag_s + (max_dist - np.sqrt(d2))
                if cand > best:
                    best = cand
                    pair_i[k] = i
                    pair_j[k] = j
                    pred[k] = diag_o
                    bo = k
                    k += 1
            diag_s = up_s
            diag_o = up_o
            S[j + 1] = best
            owner[j + 1] = bo
            left_s = S[j + 1]
            left_o = bo
        # Past the band, the row takes the left cell until the row above is as good.
        for j in range(b + 1, n + 1):
            if not left_s > S[j]:
                break
            S[j] = left_s
            owner[j] = left_o
    count = 0
    c = owner[n]
    while c >= 0:
        count += 1
        c = pred[c]
    out = np.empty((count, 2), np.int64)
    c = owner[n]
    for r in range(count - 1, -1, -1):
        out[r, 0] = pair_i[c]
        out[r, 1] = pair_j[c]
        c = pred[c]
    return out


@njit(cache=True)
def _channel_mean(a):
    """(n,) float32 mean over the channels of the (n, C) samples ``a``."""
    n = a.shape[0]
    C = a.shape[1]
    out = np.empty(n, np.float32)
    for i in range(n):
        s = 0.0
        for c in range(C):
            s += a[i, c]
        out[i] = s / C
    return out


@njit(cache=True)
def match_keypoints(a, b, lo, hi, opts):
    """Key points on the channel mean of each line, and their ordered rough matches.

    Args:
        a, b: (n1, C), (n2, C) float32 samples of line 1 and line 2.
        lo, hi: (n1,) int64 band of line-2 positions that may hold each line-1 sample's partner.
        opts: :class:`RoughOptions`.
    Returns:
        :class:`RoughMatches`; no pairs (and no jumps) when either line has fewer than two key points.
    """
    lum1 = _channel_mean(a)
    lum2 = _channel_mean(b)
    kp1 = _detect_keypoints(lum1, opts.threshold, 1)
    kp2 = _detect_keypoints(lum2, opts.threshold, 1)
    if kp1.shape[0] < 2 or kp2.shape[0] < 2:
        return RoughMatches(kp1, kp2, np.empty((0, 2), np.int64), np.empty(0, np.float32), np.empty(0, np.float32))
    d1 = _fft_descriptors(a, kp1, opts.radius, opts.ncoef)
    d2 = _fft_descriptors(b, kp2, opts.radius, opts.ncoef)
    pairs = _align_keypoints(kp1, kp2, d1, d2, lo, hi, opts.max_dist)
    return RoughMatches(kp1, kp2, pairs, _intensity_jumps(lum1)[kp1], _intensity_jumps(lum2)[kp2])


def intensity_jumps(a: np.ndarray) -> np.ndarray:
    """``da_i = |a_{i-1} - a_{i+1}| / 2`` of a (n,) intensity sequence."""
    return _intensity_jumps(np.ascontiguousarray(a, np.float32))


def detect_keypoints(a: np.ndarray, threshold: float) -> np.ndarray:
    """Indices of local maxima of the intensity jump above ``threshold``."""
    return _detect_keypoints(np.ascontiguousarray(a, np.float32), float(threshold), 1)


def fft_descriptors(a: np.ndarray, keypoints: np.ndarray, radius: int = 8, ncoef: int = 6) -> np.ndarray:
    """(len(keypoints), 2 * ncoef * C) Fourier descriptors of the key points' windows.

    ``a`` is (n,) or (n, C); channels are described together (joint unit energy).
    """
    a2 = np.ascontiguousarray(a, np.float32)
    if a2.ndim == 1:
        a2 = a2[:, None]
    return _fft_descriptors(a2, np.asarray(keypoints, np.int64), int(radius), int(ncoef))


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
    return _align_keypoints(
        p, q, np.ascontiguousarray(desc1, np.float32), np.ascontiguousarray(desc2, np.float32),
        np.asarray(lo, np.int64), np.asarray(hi, np.int64), float(max_dist),
    )
