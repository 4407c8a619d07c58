"""Search bands: the line-2 samples that may hold each line-1 sample's partner.

A point at distance ``d`` from camera 1 along a line-1 sample's ray is seen
from camera 2 under a ray angle that falls as ``d`` grows, so a range of
distances is a range of line-2 samples (:func:`depth_band`).
The range is the SIFT points' (:func:`.sefm.depth_range`) for the whole
image, or near each pixel the matches' of a coarser pyramid level
(:func:`coarse_search_band`) or of the neighbouring matches (:mod:`.propagate`),
kept as per-pixel min and max distance grids (:func:`depth_grids`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
from numba import njit, prange

from ..geometry.epipolar import LinePairs, line_alphas
from ..geometry.two_view import TwoView

if TYPE_CHECKING:
    from .sefm import CoarseLevel


def sample_alphas(lp: LinePairs, tv: TwoView) -> tuple[np.ndarray, np.ndarray]:
    """Angle from the baseline of every sample's ray, radians, flat: (N1,) for image 1 and (N2,) for image 2."""
    return line_alphas(lp, tv.K1, np.eye(3), 1), line_alphas(lp, tv.K2, tv.R.T, 2)


def search_band(lp: LinePairs, tv: TwoView, depths, slack: int, alphas: tuple[np.ndarray, np.ndarray] | None = None,
                grid: tuple[np.ndarray, np.ndarray, tuple[float, float]] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """For each line-1 sample, the line-2 sample range holding points at the given depths.

    ``depths`` is ``(dmin, dmax)``: distances from camera 1, scalars for the
    whole image or (N1,) arrays, one range per line-1 sample. With ``grid``
    ``(gmin, gmax, (sx, sy))``, a coarser level's (widened) depth grids and
    the scale of image 1 to them, a sample whose grid cell holds a range
    takes that one instead (:func:`coarse_search_band`). Returns ``lo, hi``
    (N1,) int64 positions on line 2, relative to its start, widened by
    ``slack`` samples (``hi < lo`` where the range is empty).
    """
    a1, a2 = alphas if alphas is not None else sample_alphas(lp, tv)
    n1 = len(a1)
    # Views, not copies: scalars are read through a zero stride.
    dmin = np.broadcast_to(np.asarray(depths[0], np.float64), (n1,))
    dmax = np.broadcast_to(np.asarray(depths[1], np.float64), (n1,))
    if grid is None:
        grid = (np.full((1, 1), np.inf, np.float32), np.full((1, 1), -np.inf, np.float32), (0.0, 0.0))
    gmin, gmax, (sx, sy) = grid
    start1, step1, _ = lp.side(1)
    return depth_band(a1, lp.offset1, a2, lp.offset2, dmin, dmax, float(np.linalg.norm(tv.t)), int(slack),
                      start1, step1, float(sx), float(sy), gmin, gmax)


def invert_band(lo: np.ndarray, hi: np.ndarray, off1: np.ndarray, off2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Band of line-1 positions for every line-2 sample, from the line-2 band ``lo, hi`` (N1,) of every line-1 sample.

    Returns ``first, last`` (N2,) int64, relative to line 1's start; see
    :func:`_invert_band`.
    """
    return _invert_band(np.ascontiguousarray(lo, np.int64), np.ascontiguousarray(hi, np.int64), off1, off2)


def depth_grids(uv: np.ndarray, dist: np.ndarray, shape: tuple[int, int], mask: np.ndarray | None = None,
                grids: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest distance of the points in each pixel, (height, width) float32 each.

    ``uv`` (N, 2) are COLMAP pixels of an image of ``shape``; only the points
    in ``mask`` (default all) count; pixels without a point hold inf and -inf.
    With ``grids``, the points are added to them (in place).
    """
    if grids is None:
        grids = (np.full(shape, np.inf, np.float32), np.full(shape, -np.inf, np.float32))
    mask = np.ones(len(uv), bool) if mask is None else np.ascontiguousarray(mask, bool)
    rasterise_min_max(np.ascontiguousarray(uv, np.float64), np.ascontiguousarray(dist, np.float64), mask, *grids)
    return grids


def widen(grids: tuple[np.ndarray, np.ndarray], radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Min and max depth grids, each cell taking the range of the cells within ``radius`` of it."""
    gmin, gmax = grids
    if radius > 0:
        kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        gmin = cv2.erode(gmin, kernel, borderType=cv2.BORDER_REPLICATE)
        gmax = cv2.dilate(gmax, kernel, borderType=cv2.BORDER_REPLICATE)
    return gmin, gmax


def coarse_search_band(lp: LinePairs, tv: TwoView, coarse: CoarseLevel, radius: int, depths: tuple[float, float],
                       slack: int, alphas: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`search_band` with each line-1 sample's distance range from the coarse level's matches.

    A sample's range is the smallest and largest distance the coarse level
    found within ``radius`` coarse pixels of it (so an occlusion edge keeps
    both sides, and an isolated mismatch only widens it); samples with no
    coarse match nearby keep the global ``depths``.
    """
    dm = coarse.matches
    gmin, gmax = widen(depth_grids(dm.uv1, np.linalg.norm(dm.xyz, axis=1), coarse.shape), radius)
    return search_band(lp, tv, depths, slack, alphas, (gmin, gmax, coarse.scale))


# ------------------------------------------------------------------ numba kernels


@njit(cache=True)
def _first_at_least(a, s, e, v):
    """First index i in [s, e) with a[i] >= v (a sorted), e if none."""
    while s < e:
        m = (s + e) >> 1
        if a[m] < v:
            s = m + 1
        else:
            e = m
    return s


@njit(cache=True)
def _first_above(a, s, e, v):
    """First index i in [s, e) with a[i] > v (a sorted), e if none."""
    while s < e:
        m = (s + e) >> 1
        if a[m] <= v:
            s = m + 1
        else:
            e = m
    return s


@njit(cache=True)
def _gallop(a, s, e, v, guess, strict):
    """:func:`_first_at_least` (``strict``: :func:`_first_above`), searching out from ``guess``.

    Neighbouring samples have nearby bands, so the answer is most often a
    step or two from the previous one: widen a bracket around ``guess``
    by doubling, then bisect inside it.
    """
    g = min(max(guess, s), e)
    step = 1
    if g == e or (a[g] > v if strict else a[g] >= v):  # the answer is at or below g
        hi = g
        lo = g - step
        while lo > s and (a[lo] > v if strict else a[lo] >= v):
            hi = lo
            step *= 2
            lo = g - step
        lo = max(lo, s)
    else:  # the answer is above g
        lo = min(g + 1, e)
        hi = min(g + step, e)
        while hi < e and not (a[hi] > v if strict else a[hi] >= v):
            lo = hi + 1
            step *= 2
            hi = min(g + step, e)
    if strict:
        return _first_above(a, lo, hi, v)
    return _first_at_least(a, lo, hi, v)


@njit(cache=True)
def sample_band(alpha1, a2, s2, e2, dmin, dmax, baseline, slack, ga, gb):
    """Line-2 band of one line-1 sample of ray angle ``alpha1`` (see :func:`depth_band`).

    ``a2[s2:e2]`` is line 2; ``ga``, ``gb`` are the previous sample's search
    answers (absolute indices), where the search starts. Returns ``lo, hi,
    ga, gb``.
    """
    sa = np.sin(alpha1)
    ca = np.cos(alpha1)
    hi_a = np.arctan2(dmin * sa, dmin * ca - baseline)
    if np.isfinite(dmax):
        lo_a = np.arctan2(dmax * sa, dmax * ca - baseline)
    else:
        lo_a = alpha1
    ga = _gallop(a2, s2, e2, lo_a, ga, False)
    gb = _gallop(a2, s2, e2, hi_a, gb, True)
    n2 = e2 - s2
    a = ga - s2 - slack
    b = gb - 1 - s2 + slack  # last index with a2 <= hi_a
    return min(max(a, 0), n2 - 1), min(max(b, -1), n2 - 1), ga, gb


@njit(parallel=True, cache=True)
def depth_band(a1, off1, a2, off2, dmin, dmax, baseline, slack, start, step, sx, sy, gmin, gmax):
    """For each line-1 sample, the line-2 sample range holding points at distances [dmin, dmax].

    A point at distance ``d`` along the ray of angle ``a1`` is seen from camera 2
    under ``a2 = atan2(d sin a1, d cos a1 - B)``, falling from pi (d = 0) to
    ``a1`` (d = inf); ``a2`` increases along each line 2.

    The range of sample ``k`` of line ``l`` (at ``start[l] + k step[l]``,
    COLMAP pixels of image 1) is cell ``floor(x sx), floor(y sy)`` of the
    ``gmin``/``gmax`` grids (a coarser level's distance range near each
    pixel) where it is finite, else ``dmin``/``dmax``. Read here and used at once, so
    no (N1,) range arrays are made: fresh memory is what a large pair pays
    most for. A 1x1 grid of inf leaves every sample its ``dmin``/``dmax``.

    Args:
        a1, a2: (N1,), (N2,) sample ray angles.
        dmin, dmax: (N1,) distance range per sample (``dmax`` may be inf;
            a broadcast view is fine).
    Returns:
        lo, hi (N1,) int64 positions on line 2 relative to its start, widened
        by ``slack`` samples and clipped (``hi < lo`` when empty).
    """
    L = off1.shape[0] - 1
    N1 = a1.shape[0]
    H, W = gmin.shape
    lo = np.empty(N1, np.int64)
    hi = np.empty(N1, np.int64)
    for ll in prange(L):
        l = np.int64(ll)
        s2 = off2[l]
        e2 = off2[l + 1]
        ga = s2
        gb = s2
        for k in range(off1[l + 1] - off1[l]):
            i = off1[l] + k
            c = min(max(int(np.floor((start[l, 0] + k * step[l, 0]) * sx)), 0), W - 1)
            r = min(max(int(np.floor((start[l, 1] + k * step[l, 1]) * sy)), 0), H - 1)
            d0 = np.float64(dmin[i])
            d1 = np.float64(dmax[i])
            if np.isfinite(gmin[r, c]):
                d0 = np.float64(gmin[r, c])
                d1 = np.float64(gmax[r, c])
            lo[i], hi[i], ga, gb = sample_band(a1[i], a2, s2, e2, d0, d1, baseline, slack, ga, gb)
    return lo, hi


@njit(parallel=True, cache=True)
def _invert_band(lo, hi, off1, off2):
    """Band of line-1 positions for every line-2 sample, from the line-2 band of every line-1 sample.

    The bands are first made monotone (only ever widened): ``hi`` as a running
    maximum along the line, ``lo`` as a running minimum from its end. Line-2
    sample ``k`` may then match line-1 samples ``first..last``: the first
    whose ``hi`` reaches ``k`` and the last whose ``lo`` does not pass it.
    """
    L = off1.shape[0] - 1
    N2 = off2[L]
    first = np.empty(N2, np.int64)
    last = np.empty(N2, np.int64)
    for ll in prange(L):
        l = np.int64(ll)
        s1 = off1[l]
        n1 = off1[l + 1] - s1
        s2 = off2[l]
        n2 = off2[l + 1] - s2
        hi_m = np.empty(n1, np.int64)
        lo_m = np.empty(n1, np.int64)
        run = np.int64(-(1 << 40))
        for i in range(n1):
            run = max(run, hi[s1 + i])
            hi_m[i] = run
        run = np.int64(1 << 40)
        for i in range(n1 - 1, -1, -1):
            run = min(run, lo[s1 + i])
            lo_m[i] = run
        p = 0  # first i with hi_m[i] >= k
        q = 0  # first i with lo_m[i] > k
        for k in range(n2):
            while p < n1 and hi_m[p] < k:
                p += 1
            while q < n1 and lo_m[q] <= k:
                q += 1
            first[s2 + k] = min(max(p, 0), n1 - 1)
            last[s2 + k] = min(max(q - 1, -1), n1 - 1)
    return first, last


@njit(cache=True)
def rasterise_min_max(uv, dist, mask, gmin, gmax):
    """Lower ``gmin`` and raise ``gmax`` (H, W) to the ``dist`` of each point in ``mask``, in place.

    Point ``k`` falls in cell ``floor(uv[k])`` (COLMAP pixels of the grid's
    image); points outside the grid are skipped. Fresh grids start at inf
    and -inf.
    """
    height, width = gmin.shape
    for k in range(uv.shape[0]):
        if not mask[k]:
            continue
        c = int(np.floor(uv[k, 0]))
        r = int(np.floor(uv[k, 1]))
        if 0 <= r < height and 0 <= c < width:
            d = np.float32(dist[k])
            if d < gmin[r, c]:
                gmin[r, c] = d
            if d > gmax[r, c]:
                gmax[r, c] = d
