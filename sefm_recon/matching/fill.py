"""Gap filling: partners for the unmatched samples between matched ones on a line.

Scanline DP leaves samples without a partner where a segment failed S_v or a
run was judged occluded. :func:`fill_gaps` searches the partner of each sample
of a short gap near the interpolation of its matched neighbours,
:func:`fill_from_band` searches the whole band where a coarser level made it
narrow (both by window correlation, :mod:`.zncc`), and :func:`bridge_gaps`
interpolates short gaps inside a surface where no correlation decided. A gap
that is a depth edge rather than a surface is left alone.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .zncc import zncc_search


@njit(inline="always")
def _surface_gap(span, length, max_scale):
    """Whether partners ``span`` line-2 samples apart can bound a gap ``length`` samples long on one surface.

    A gap whose partners span more than ``max_scale`` times fewer (a fold:
    samples hidden in view 2) or more (hidden in view 1) samples than it has,
    or none, is a depth edge.
    """
    return span > 0 and max_scale * span >= length and span <= max_scale * length


@njit(parallel=True, cache=True)
def fill_gaps(I1, off1, I2, off2, j, max_gap, radius, half, min_zncc, max_scale=np.inf):
    """Fill short gaps of unmatched samples between matched ones on each line.

    The partner of a sample in a gap is predicted by interpolating its matched
    neighbours on the line, then searched within ``radius`` samples of the
    prediction by ZNCC over the window of ``2 half + 1`` samples and all
    channels (the neighbour lines: a 2-D patch), refined by a parabola.
    Accepted when the correlation reaches ``min_zncc``. A gap that is a depth
    edge, not a surface (:func:`_surface_gap`), is left alone: its samples
    are occluded in one view and the interpolation would put them on the
    wrong surface. Returns the filled copy of ``j`` and a mask of the filled
    samples.
    """
    L = off1.shape[0] - 1
    out = j.copy()
    filled = np.zeros(j.shape[0], np.bool_)
    for l in prange(L):
        s1 = off1[l]
        e1 = off1[l + 1]
        a = I1[s1:e1]
        b = I2[off2[l]:off2[l + 1]]
        n = e1 - s1
        prev = -1
        for i in range(n + 1):
            if i < n and np.isnan(j[s1 + i]):
                continue
            if prev >= 0 and i < n and 1 < i - prev <= max_gap + 1:
                j0 = j[s1 + prev]
                j1 = j[s1 + i]
                if _surface_gap(j1 - j0, i - prev, max_scale):
                    for g in range(prev + 1, i):
                        pred = j0 + (j1 - j0) * (g - prev) / (i - prev)
                        best, pos = zncc_search(a, g, b, pred - radius, 2 * radius + 1, half, min_zncc)
                        if best >= min_zncc:
                            out[s1 + g] = pos
                            filled[s1 + g] = True
            prev = i
    return out, filled


@njit(parallel=True, cache=True)
def fill_from_band(I1, off1, I2, off2, j, lo, hi, max_width, half, min_zncc, max_scale=np.inf):
    """Match unmatched samples whose search band is narrow (a coarser level bounded it).

    Where the band ``[lo, hi]`` of line-2 positions spans at most ``max_width``
    samples, the partner is the band's best ZNCC over the window of ``2 half + 1``
    samples and all channels, refined by a parabola, accepted when the
    correlation reaches ``min_zncc``. Samples in a gap between matches that is
    a depth edge (:func:`_surface_gap`, ``max_scale``) are left alone: the
    band spans both surfaces there. Returns the filled copy of ``j`` and a
    mask of the filled samples.
    """
    L = off1.shape[0] - 1
    out = j.copy()
    filled = np.zeros(j.shape[0], np.bool_)
    for ll in prange(L):
        l = np.int64(ll)
        s1 = off1[l]
        a = I1[s1:off1[l + 1]]
        b = I2[off2[l]:off2[l + 1]]
        n = off1[l + 1] - s1
        # The next matched sample of every sample (for the gap test), filled right to left.
        nxt = np.full(n, -1, np.int64)
        if max_scale < np.inf:
            for i in range(n - 2, -1, -1):
                nxt[i] = i + 1 if not np.isnan(j[s1 + i + 1]) else nxt[i + 1]
        prv = -1
        for i in range(n):
            if not np.isnan(j[s1 + i]):
                prv = i
                continue
            if hi[s1 + i] < lo[s1 + i] or hi[s1 + i] - lo[s1 + i] + 1 > max_width:
                continue
            if prv >= 0 and nxt[i] >= 0 and not _surface_gap(j[s1 + nxt[i]] - j[s1 + prv], nxt[i] - prv, max_scale):
                continue
            best, pos = zncc_search(a, i, b, float(lo[s1 + i]), hi[s1 + i] - lo[s1 + i] + 1, half,
                                     min_zncc)
            if best < min_zncc:
                continue
            out[s1 + i] = pos
            filled[s1 + i] = True
    return out, filled


@njit(parallel=True, cache=True)
def bridge_gaps(j, off1, max_gap, min_slope, max_slope, slope_tol=np.inf):
    """Interpolate the partners of gaps of at most ``max_gap`` samples between matched ones on each line.

    Where neither the DP nor the window correlations placed a partner (low
    texture, noise), a short gap inside a surface is still a surface: its
    end partners advance ``min_slope`` to ``max_slope`` samples per sample,
    and the matched samples up to 4 beyond each end continue at that slope
    within ``slope_tol`` (a depth edge or an occlusion bends it). Returns
    the copy and the mask of bridged samples.
    """
    L = off1.shape[0] - 1
    out = j.copy()
    filled = np.zeros(j.shape[0], np.bool_)
    for l in prange(L):
        s1 = off1[l]
        n = off1[l + 1] - s1
        prev = -1
        for i in range(n):
            if np.isnan(j[s1 + i]):
                continue
            if prev >= 0 and 1 < i - prev <= max_gap + 1:
                j0 = j[s1 + prev]
                slope = (j[s1 + i] - j0) / (i - prev)
                # the partners on either side must continue at the gap's slope
                ok = min_slope <= slope <= max_slope
                for side in range(2):
                    a0 = prev if side == 0 else i
                    far = -1
                    for q in range(1, 5):
                        k2 = a0 - q if side == 0 else a0 + q
                        if k2 < 0 or k2 >= n:
                            break
                        if not np.isnan(j[s1 + k2]):
                            far = k2
                    if far < 0:
                        ok = False
                    else:
                        sl = (j[s1 + a0] - j[s1 + far]) / (a0 - far)
                        if abs(sl - slope) > slope_tol:
                            ok = False
                if ok:
                    for g in range(prev + 1, i):
                        out[s1 + g] = j0 + slope * (g - prev)
                        filled[s1 + g] = True
            prev = i
    return out, filled

