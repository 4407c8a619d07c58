"""Inconsistency handling (paper §4.5), and a 2-D check across lines (an addition).

S_v, the segment validity, is applied inside the line kernel
(:func:`.dense.match_lines`), where the key points are at hand
(:func:`segment_valid`). S_p, the pixel validity from depth jumps along a line
(:func:`depth_continuity`), and the 2-D check of each match against the
matches of the neighbouring lines (:func:`neighbour_consistency`) need
triangulated depths: :func:`validated_points` runs both on the matched samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..config import Config
from ..geometry.epipolar import LinePairs
from ..geometry.two_view import TwoView
from .points import line_points


class SegmentValidity(NamedTuple):
    """Settings of S_v (:func:`segment_valid`)."""

    max_unmatched: int  #: unmatched strong key points a segment may hold
    strength: float  #: a key point is strong at a jump of this many key-point thresholds


class NeighbourCheck(NamedTuple):
    """Settings of the 2-D check (:func:`grid_median_check`)."""

    radius: int  #: window half size, pixels
    tol: float  #: largest difference from the neighbours' median (in the checked value's unit)
    min_support: int  #: neighbours needed to judge a point
    drop_isolated: bool = False  #: drop the points with fewer neighbours (instead of keeping them)
    bins: int = 0  #: > 0: estimate the median too, to within ``2 tol / bins``


@njit(cache=True)
def _count_strong(jump, first, last, strong):
    """Key points with index in (first, last) whose ``jump`` (one per key point) is at least ``strong``."""
    c = 0
    for k in range(first + 1, last):
        if jump[k] >= strong:
            c += 1
    return c


@njit(cache=True)
def segment_valid(jump1, jump2, pairs, k, strong, max_unmatched):
    """S_v (paper §4.5): whether the segment between rough matches ``k`` and ``k + 1`` is free of occlusions.

    A key point between the segment's ends in either line, unmatched, means
    something seen in one view only; the segment is valid while at most
    ``max_unmatched`` such key points have a jump of ``strong`` or more.
    ``jump1``, ``jump2`` are the key points' jumps, ``pairs`` (k, 2) the
    rough matches (:class:`.rough.RoughMatches`).
    """
    unmatched = (_count_strong(jump1, pairs[k, 0], pairs[k + 1, 0], strong)
                 + _count_strong(jump2, pairs[k, 1], pairs[k + 1, 1], strong))
    return unmatched <= max_unmatched


@njit(parallel=True, cache=True)
def depth_runs_filter(depth, line_of, jump, min_run, mask):
    """S_p (paper §4.5): keep points whose depth continues their neighbours'.

    Points are in line order (``line_of`` non-decreasing, samples increasing
    along each line); only those with ``mask`` set take part (the others are
    skipped, as if absent, and not kept). A relative depth change above
    ``jump`` between consecutive points starts a new run; runs shorter than
    ``min_run`` points are isolated depth spikes (mismatches) and are dropped.
    Returns a keep mask.
    """
    n = depth.shape[0]
    keep = np.zeros(n, np.bool_)
    # Line boundaries.
    starts = np.empty(n + 1, np.int64)
    ns = 0
    for i in range(n):
        if i == 0 or line_of[i] != line_of[i - 1]:
            if i > 0 and line_of[i] < line_of[i - 1]:
                raise ValueError("points must be sorted by line")
            starts[ns] = i
            ns += 1
    starts[ns] = n
    for s in prange(ns):
        a = starts[s]
        e = starts[s + 1]
        first = a  # first point of the current run
        prev = -1  # last point taken part
        count = 0  # points of the current run
        for i in range(a, e + 1):
            if i < e and not mask[i]:
                continue
            brk = i == e
            if not brk and prev >= 0:
                d0 = depth[prev]
                d1 = depth[i]
                brk = abs(d1 - d0) > jump * min(d0, d1)
            if brk:
                if count >= min_run:
                    for k in range(first, i):
                        if mask[k]:
                            keep[k] = True
                first = i
                count = 0
            prev = i
            count += 1
    return keep


@njit(cache=True)
def _rasterise(uv, value, mask, height, width):
    """(height, width) float32 grid of ``value`` at ``floor(uv)`` of the masked points.

    The first point of a cell wins; cells without one hold NaN.
    """
    grid = np.full((height, width), np.nan, np.float32)
    for k in range(uv.shape[0]):
        if not mask[k]:
            continue
        r = int(np.floor(uv[k, 1]))
        c = int(np.floor(uv[k, 0]))
        if 0 <= r < height and 0 <= c < width and np.isnan(grid[r, c]):
            grid[r, c] = value[k]
    return grid


@njit(inline="always")
def _neighbours(grid, r, c, radius, buf):
    """Copy the values of the other cells of the ``(2 radius + 1)^2`` window at (r, c) into ``buf``.

    Returns their count (cells holding NaN are skipped).
    """
    m = 0
    for rr in range(max(r - radius, 0), min(r + radius + 1, grid.shape[0])):
        for cc in range(max(c - radius, 0), min(c + radius + 1, grid.shape[1])):
            v = grid[rr, cc]
            if not np.isnan(v) and not (rr == r and cc == c):
                buf[m] = v
                m += 1
    return m


@njit(parallel=True, cache=True)
def grid_median_check(uv, value, mask, height, width, check):
    """2-D consistency: compare each point's value with the median of its neighbours.

    Points with ``mask`` set are rasterised into a (height, width) grid at
    ``floor(uv)`` (the first point of a cell wins); such a point is kept when
    at least ``min_support`` other cells of its ``(2 radius + 1)^2`` window
    hold a value and the point is within ``tol`` of their median; a point with
    too few neighbours to judge is kept, unless ``drop_isolated`` (the
    settings are ``check``'s, a :class:`NeighbourCheck`). The median
    test is done by counting, without sorting: the median lies more than
    ``tol`` above the point exactly when more than half of the neighbours do
    (with an even count: when the lower middle value does). Points without
    ``mask`` are not kept.

    With ``bins`` > 0 the median itself is estimated for the kept, judged
    points, without sorting either: the neighbours within ``tol`` of the point
    go into ``bins`` bins of width ``2 tol / bins``, and the middle rank's
    value is the mean of its bin (exact where it falls outside the range),
    so within one bin width of the exact median.

    Args:
        uv: (N, 2) positions (x, y), COLMAP pixels; value, mask: (N,).
    Returns (keep (N,) bool, support (N,) int32, median (N,): the
    estimate, or the point's own value where not estimated; with ``bins``
    = 0, ``value`` itself).
    """
    radius, tol, min_support, drop_isolated, bins = (check.radius, check.tol, check.min_support,
                                                     check.drop_isolated, check.bins)
    n = uv.shape[0]
    grid = _rasterise(uv, value, mask, height, width)
    keep = np.zeros(n, np.bool_)
    support = np.zeros(n, np.int32)
    # The check alone returns the values themselves: a copy costs 24 MB of fresh pages at 2000 px.
    median = value.astype(np.float64) if bins > 0 else value
    nchunk = min(n, 256)
    width_bin = 2.0 * tol / max(bins, 1)
    for ch in prange(nchunk):
        buf = np.empty((2 * radius + 1) ** 2, np.float32)  # one per chunk, not per point
        count = np.zeros(max(bins, 1), np.int64)
        total = np.zeros(max(bins, 1))
        for k in range(ch * n // nchunk, (ch + 1) * n // nchunk):
            if not mask[k]:
                continue
            r = int(np.floor(uv[k, 1]))
            c = int(np.floor(uv[k, 0]))
            x = value[k]
            m = _neighbours(grid, r, c, radius, buf)
            above = 0
            below = 0
            for q in range(m):
                above += buf[q] > x + tol
                below += buf[q] < x - tol
            support[k] = m
            if m < min_support:
                keep[k] = not drop_isolated
                continue
            keep[k] = not (2 * above > m or 2 * below > m)
            if bins == 0 or not keep[k]:
                continue
            count[:] = 0
            total[:] = 0.0
            max_below = -np.inf
            min_above = np.inf
            for q in range(m):
                v = buf[q]
                if v < x - tol:
                    max_below = max(max_below, v)
                elif v > x + tol:
                    min_above = min(min_above, v)
                else:
                    bq = min(int((v - (x - tol)) / width_bin), bins - 1)
                    count[bq] += 1
                    total[bq] += v
            est = 0.0
            # The two middles (the same one for an odd count). A kept point has
            # at most half its neighbours below (above) the range, so a middle
            # outside it is the largest value below (smallest above) it.
            for rank in ((m - 1) // 2, m // 2):
                if rank < below:
                    est += max_below
                elif rank >= m - above:
                    est += min_above
                else:
                    cum = below
                    for bq in range(bins):
                        cum += count[bq]
                        if rank < cum:
                            est += total[bq] / count[bq]
                            break
            median[k] = 0.5 * est
    return keep, support, median


def depth_continuity(depth: np.ndarray, line: np.ndarray, jump: float = 0.05, min_run: int = 5,
                     mask: np.ndarray | None = None) -> np.ndarray:
    """S_p: keep mask of points whose depth continues along their epipolar line.

    Args:
        depth: (N,) depth of each match (any positive unit), in line order.
        line: (N,) line index of each match, non-decreasing.
        jump: relative depth change between consecutive points that counts as a jump.
        min_run: runs between jumps shorter than this are dropped as spikes.
        mask: (N,) points that take part (default all); the others are skipped and not kept.
    """
    depth = np.ascontiguousarray(depth, np.float64)
    line = np.ascontiguousarray(line, np.int64)
    if len(depth) == 0:
        return np.zeros(0, bool)
    mask = np.ones(len(depth), bool) if mask is None else np.ascontiguousarray(mask, bool)
    return depth_runs_filter(depth, line, float(jump), int(min_run), mask)


def neighbour_consistency(uv: np.ndarray, inv_depth: np.ndarray, shape: tuple[int, int], radius: int = 2,
                          tol: float = 1e-3, min_support: int = 6, drop_isolated: bool = False,
                          mask: np.ndarray | None = None) -> np.ndarray:
    """2-D consistency across neighbouring line pairs: keep mask (N,).

    Scanline DP decides each line alone, which leaves streaks: runs of wrong
    matches that disagree with the lines beside them. Each match's inverse
    depth (proportional to disparity) is compared with the median of the other
    matches in its ``(2 radius + 1)^2`` pixel window of image 1; matches farther
    than ``tol`` from it are dropped (``tol`` in inverse-depth units: a pixel
    of disparity is about ``1 / (f * baseline)``). Matches with fewer than
    ``min_support`` neighbours are kept, or dropped with ``drop_isolated``
    (an isolated match in a dense field is most often a wrong one).

    Args:
        uv: (N, 2) positions in image 1 (COLMAP pixels). shape: (height, width).
        mask: (N,) matches that take part (default all); the others are not kept.
    """
    # The same pass without the median estimate (bins = 0).
    return neighbour_median(uv, inv_depth, shape, radius, tol, min_support, drop_isolated, mask, bins=0)[0]


def neighbour_median(uv: np.ndarray, inv_depth: np.ndarray, shape: tuple[int, int], radius: int = 2,
                     tol: float = 1e-3, min_support: int = 6, drop_isolated: bool = False,
                     mask: np.ndarray | None = None, bins: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """:func:`neighbour_consistency`, and the neighbours' median: ``keep`` (N,), ``median`` (N,).

    The median is also the better inverse depth of a kept match: each line's
    DP and sub-pixel step place a partner from that line's samples alone, so
    on a surface the partners scatter by a fraction of a pixel around the
    truth, most where an edge runs along the line (the line then says little
    about where along it the partner lies). Being a median, it keeps straight
    depth edges. It is estimated to within ``2 tol / bins`` (one bin of a
    histogram of the neighbours within ``tol``; exact ranks cost four times
    the check). Dropped matches, those with fewer than ``min_support``
    neighbours and those without ``mask`` get their own value; so does every
    match with ``bins`` = 0 (the check alone).
    """
    inv_depth = np.ascontiguousarray(inv_depth, np.float64)
    if len(uv) == 0:
        return np.zeros(0, bool), np.zeros(0)
    mask = np.ones(len(uv), bool) if mask is None else np.ascontiguousarray(mask, bool)
    check = NeighbourCheck(int(radius), float(tol), int(min_support), bool(drop_isolated), int(bins))
    keep, _, median = grid_median_check(np.ascontiguousarray(uv, np.float64), inv_depth, mask,
                                        int(shape[0]), int(shape[1]), check)
    return keep, median


@dataclass
class ValidatedPoints:
    """The matched samples as points, and which of them the validity checks keep (:func:`validated_points`)."""

    idx: np.ndarray  #: (M,) int64 flat line-1 sample index
    line: np.ndarray  #: (M,) int64 line pair
    uv1: np.ndarray  #: (M, 2) COLMAP pixels in image 1
    uv2: np.ndarray  #: (M, 2) in image 2; (0, 2) where not asked for or where ``median`` replaces it
    X: np.ndarray  #: (M, 3) midpoints, camera-1 frame; (0, 3) as ``uv2``
    dist: np.ndarray  #: (M,) distance from camera 1
    keep: np.ndarray  #: (M,) bool: valid, kept by S_p and the 2-D check
    median: np.ndarray | None = None  #: (M,) the 2-D check's neighbour median of each distance, where asked for


def validated_points(j: np.ndarray, cost: np.ndarray, lp: LinePairs, tv: TwoView, shape: tuple[int, int],
                     cfg: Config, median: bool = False, pairs: bool = True) -> ValidatedPoints:
    """Matched samples -> pixel pairs, points and the validity mask (S_p, then the 2-D check).

    ``j`` (N1,) partner positions on line 2 (NaN: none), ``cost`` (N1,) their
    DP cost (above ``validity.max_cost``: dropped); ``shape`` (height, width)
    of image 1. With ``median`` and the 2-D check on, the points also get the
    check's neighbour median of each distance (:func:`neighbour_median`).
    ``uv2`` and ``X`` are empty without ``pairs``, and where the median
    replaces them.
    """
    v = cfg.validity
    median = median and v.neighbour_tol_px > 0
    pts = line_points(j, cost, v.max_cost, np.radians(v.min_tri_angle_deg), lp, tv, pairs and not median)
    keep = depth_continuity(pts.dist, pts.line, v.sp_depth_jump, v.sp_min_run, mask=pts.valid)
    med = None
    if v.neighbour_tol_px > 0:
        # One pixel of disparity is about 1 / (f * B) in inverse depth.
        scale = float(tv.K1[0, 0] * np.linalg.norm(tv.t))
        args = (pts.uv1, scale / pts.dist, shape, v.neighbour_radius, v.neighbour_tol_px, v.neighbour_support,
                v.drop_isolated, keep)
        if median:
            keep, inv = neighbour_median(*args)
            med = scale / inv
        else:
            keep = neighbour_consistency(*args)
    return ValidatedPoints(pts.idx, pts.line, pts.uv1, pts.uv2, pts.X, pts.dist, keep, med)
