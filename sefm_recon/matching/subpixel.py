"""Sub-pixel refinement of the partners by window correlation (an addition to the paper).

The DP places each partner on its (resampled) sample grid. A parabola through
the window ZNCC (:mod:`.zncc`) at the partner and its two neighbours gives the
sub-sample position. On a slanted surface line 2's window is stretched by the
local slope of the partners (:func:`_local_slope`); where depth changes across
lines, each neighbour line's window is moved by the shear read from the
matches of the neighbouring line pairs (:func:`line_shear`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..config import Config
from ..geometry.epipolar import LinePairs
from .zncc import zncc3, zncc3_sheared


class SubpixelOptions(NamedTuple):
    """Settings of :func:`refine_subpixel`."""

    half: int  #: ZNCC window half length, samples
    max_shift: float = 1.0  #: larger parabola shifts (no clear peak) are not applied, samples
    slope_radius: int = 0  #: samples on either side that give the partners' local slope (0: no stretching)
    min_stretch: float = 0.1  #: slopes closer to 1 than this keep the plain window
    min_shear: float = 0.1  #: shears below this keep the unmoved window, line-2 samples per line


class Channels(NamedTuple):
    """The columns of the line samples a window reads: ``c0`` up to ``c1`` (exclusive; -1: all).

    They are neighbour lines ``o_first, o_first + 1, ...`` (0: the line
    itself), ``cc`` channels each (:func:`sefm_recon.geometry.epipolar.sample_line_channels`).
    """

    c0: int = 0
    c1: int = -1
    o_first: int = 0
    cc: int = 1


@njit(cache=True)
def _local_slope(j, i, n, r):
    """Line-2 samples per line-1 sample around sample ``i`` of a line.

    The slope between the matched samples farthest from ``i`` within ``r`` on
    either side (``i`` itself where a side has none). ``j`` (n,) partner
    positions of the line's samples (NaN: none). Returns 1.0 with no partner
    on either side; clipped to [0.5, 2].
    """
    il = i
    for k in range(max(0, i - r), i):
        if not np.isnan(j[k]):
            il = k
            break
    ir = i
    for k in range(min(n - 1, i + r), i, -1):
        if not np.isnan(j[k]):
            ir = k
            break
    if ir == il:
        return 1.0
    # j[i] itself is matched (refinement only asks for matched samples), so g is finite.
    return min(max((j[ir] - j[il]) / (ir - il), 0.5), 2.0)



@njit(cache=True)
def _index_at(a, target, k):
    """Fractional index of ``target`` in a line's monotone samples ``a`` (n,), by Newton steps from ``k``.

    Linear between samples; NaN where ``target`` is outside the line.
    """
    n = a.shape[0]
    if n < 2:
        return np.nan
    for _ in range(8):
        q = min(max(int(np.floor(k)), 0), n - 2)
        slope = a[q + 1] - a[q]
        if slope == 0.0:
            return np.nan
        k = q + (target - a[q]) / slope
        if k < -0.5 or k > n - 0.5:
            return np.nan
        if q <= k <= q + 1:
            return k
    return np.nan



@njit(cache=True)
def _lerp_match(j, k):
    """Partner position at fractional index ``k`` between two matched samples of a line.

    NaN unless both are matched and their partners 2 or fewer samples apart.
    """
    q = int(np.floor(k))
    if q < 0 or q + 1 >= j.shape[0]:
        return np.nan
    u = j[q]
    v = j[q + 1]
    if np.isnan(u) or np.isnan(v) or abs(v - u) > 2.0:
        return np.nan
    return u + (k - q) * (v - u)



@njit(parallel=True, cache=True)
def line_shear(j, a1, off1, a2, off2, next_line, radius, max_shear):
    """How far a match moves along line 2 per neighbour line, per matched line-1 sample.

    Neighbour line ``o`` of a sample is the ray at the same angle ``alpha`` in
    the half-plane ``o`` steps over, in both images; ``next_line[l]`` is the
    line pair of the next half-plane (-1 if none) and ``next_line``'s inverse
    the previous one. The partner of line ``l``'s sample ``i`` on the next
    line is that line's match at the same ``alpha_1``, taken to line ``l``'s
    samples at the same ``alpha_2``; its distance from ``j[i]``, against the
    previous line's, averaged over the matched samples within ``radius``
    (leaving out shears over ``max_shear``: across a depth edge), is the
    shear (line-2 samples per line). Zero where unknown: a surface seen face
    on has none.

    Args:
        j: (N1,) partner positions (relative to line 2's start), NaN: none.
        a1, a2: (N1,), (N2,) ray angles from the baseline of the samples.
        next_line: (L,) int64.
    Returns:
        (N1,) float32.
    """
    L = off1.shape[0] - 1
    prev_line = np.full(L, -1, np.int64)
    for l in range(L):
        if next_line[l] >= 0:
            prev_line[next_line[l]] = l
    out = np.zeros(j.shape[0], np.float32)
    for ll in prange(L):
        l = np.int64(ll)
        s1 = off1[l]
        n1 = off1[l + 1] - s1
        b2 = a2[off2[l]:off2[l + 1]]
        raw = np.zeros(n1)  # the sum over both sides, then their mean (NaN where neither gave one)
        side_cnt = np.zeros(n1, np.int64)
        for side in range(2):
            m = next_line[l] if side == 1 else prev_line[l]
            if m < 0:
                continue
            am = a1[off1[m]:off1[m + 1]]
            jm = j[off1[m]:off1[m + 1]]
            bm = a2[off2[m]:off2[m + 1]]
            sign = 1.0 if side == 1 else -1.0
            k = 0.0
            last = 0
            for i in range(n1):
                jl = j[s1 + i]
                if np.isnan(jl):
                    continue
                # The lines are almost parallel: the last sample's offset is a close first guess.
                kk = _index_at(am, a1[s1 + i], k + (i - last))
                if np.isnan(kk):
                    continue
                k = kk
                last = i
                jk = _lerp_match(jm, k)
                if np.isnan(jk):
                    continue
                q = min(int(jk), bm.shape[0] - 2)
                k2 = _index_at(b2, bm[q] + (jk - q) * (bm[q + 1] - bm[q]), jl)
                if not np.isnan(k2):
                    raw[i] += sign * (k2 - jl)
                    side_cnt[i] += 1
        for i in range(n1):
            raw[i] = raw[i] / side_cnt[i] if side_cnt[i] > 0 else np.nan
        # The mean over a sliding window, as running sums; shears over
        # max_shear (and NaN) are across a depth edge and left out.
        tot = 0.0
        cnt = 0
        for k in range(min(n1, radius)):
            if abs(raw[k]) <= max_shear:
                tot += raw[k]
                cnt += 1
        for i in range(n1):
            k = i + radius
            if k < n1 and abs(raw[k]) <= max_shear:
                tot += raw[k]
                cnt += 1
            k = i - radius - 1
            if k >= 0 and abs(raw[k]) <= max_shear:
                tot -= raw[k]
                cnt -= 1
            if cnt > 0 and not np.isnan(j[s1 + i]):
                out[s1 + i] = tot / cnt
    return out



@njit(parallel=True, cache=True)
def refine_subpixel(I1, off1, I2, off2, j, opts, channels, shear=None):
    """Sub-pixel partner positions: a parabola through the ZNCC at j - 1, j, j + 1.

    The DP places partners on its sample grid (after the segment resampling);
    the window correlation over the channels (neighbour lines included) is
    smooth near its peak, and its parabola vertex is the sub-sample position.
    ``opts`` (:class:`SubpixelOptions`) says how; ``channels`` (:class:`Channels`)
    which columns of the samples take part (a view, so the caller need not
    copy the samples of the lines it uses) and which neighbour lines they are.
    With ``shear`` (N1,) (:func:`line_shear`), each neighbour line's window
    is moved along line 2 by its shear.

    Args:
        I1, I2: (N1, C), (N2, C) float32 line samples; off1, off2: (L + 1,) int64 line offsets.
        j: (N1,) partner positions on line 2, samples from its start (NaN: none).
    Returns:
        the refined copy of ``j``, and (N1,) float32 the ZNCC at the DP's
        position (NaN where unmatched, -2 where the window is flat or, cut at
        the line ends, shorter than ``half + 1`` samples).
    """
    half = opts.half
    c0 = channels.c0
    L = off1.shape[0] - 1
    ce = I1.shape[1] if channels.c1 < 0 else channels.c1
    out = j.copy()
    zncc = np.full(j.shape[0], np.nan, np.float32)
    for l in prange(L):
        s1 = off1[l]
        e1 = off1[l + 1]
        a = I1[s1:e1, c0:ce]
        b = I2[off2[l]:off2[l + 1], c0:ce]
        for i in range(e1 - s1):
            jj = j[s1 + i]
            if np.isnan(jj):
                continue
            g = _local_slope(j[s1:e1], i, e1 - s1, opts.slope_radius) if opts.slope_radius > 0 else 1.0
            if abs(g - 1.0) < opts.min_stretch:
                g = 1.0
            h = 0.0 if shear is None else shear[s1 + i]
            if abs(h) < opts.min_shear:
                h = 0.0
            if g == 1.0 and h == 0.0:
                zl, z0, zr = zncc3(a, i, b, jj, half)
            else:
                zl, z0, zr = zncc3_sheared(a, i, b, jj, half, g, h, channels.o_first, channels.cc)
            zncc[s1 + i] = z0
            if z0 <= -2.0 or zl <= -2.0 or zr <= -2.0:
                continue
            den = zl - 2.0 * z0 + zr
            if den >= 0.0:
                continue
            off = 0.5 * (zl - zr) / den
            if abs(off) <= opts.max_shift:
                out[s1 + i] = jj + off
    return out, zncc



def next_line(lp: LinePairs, step: float) -> np.ndarray:
    """(L,) int64: the line pair whose half-plane is ``step`` line steps past each one's (-1 if none).

    Line pairs are ordered by half-plane angle, but lines that cross only one
    image are left out, so the neighbour half-plane is not always the next pair.
    """
    L = len(lp)
    out = np.full(L, -1, np.int64)
    want = step * lp.phi_step
    for shift in (1, -1):
        m = (np.arange(L) + shift) % L
        d = (lp.phi[m] - lp.phi + np.pi) % (2 * np.pi) - np.pi
        ok = (np.abs(d - want) <= 0.01 * abs(want)) & (m != np.arange(L))
        out[ok] = m[ok]
    return out


def inner_channels(I: np.ndarray, neighbours: int, keep: int) -> tuple[int, int]:
    """Columns ``c0:c1`` of the centre line and its ``keep`` nearest neighbour lines on each side.

    ``I`` is (N, (2 neighbours + 1) C), neighbour-major (:func:`sefm_recon.geometry.epipolar.sample_line_channels`).
    """
    if keep >= neighbours:
        return 0, I.shape[1]
    c = I.shape[1] // (2 * neighbours + 1)
    return (neighbours - keep) * c, (neighbours + keep + 1) * c


def refine(I1: np.ndarray, I2: np.ndarray, lp: LinePairs, j: np.ndarray, alphas: tuple[np.ndarray, np.ndarray],
           cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """``dense.subpixel_iterations`` rounds of :func:`refine_subpixel` with the ``dense.subpixel_*`` settings.

    ``I1``, ``I2`` are the line samples with ``lines.neighbours`` neighbour
    lines on each side; ``alphas`` the samples' ray angles (for the shear).
    Returns the refined ``j`` (N1,) and the last round's ZNCC (N1,) float32.
    """
    d = cfg.dense
    nb = cfg.lines.neighbours
    off1, off2 = lp.offset1, lp.offset2
    c0, c1 = inner_channels(I1, nb, d.subpixel_neighbours)
    shear = None
    if d.subpixel_shear_radius > 0 and nb > 0:
        shear = line_shear(j, alphas[0], off1, alphas[1], off2, next_line(lp, cfg.lines.neighbour_step),
                           d.subpixel_shear_radius, d.subpixel_max_shear)
    opts = SubpixelOptions(d.subpixel_half_window, 1.0, d.subpixel_slope_radius, d.subpixel_min_stretch,
                           d.subpixel_min_shear)
    channels = Channels(c0, c1, -min(nb, d.subpixel_neighbours), I1.shape[1] // (2 * nb + 1))
    zncc = None
    for _ in range(d.subpixel_iterations):
        j, zncc = refine_subpixel(I1, off1, I2, off2, j, opts, channels, shear)
    return j, zncc
