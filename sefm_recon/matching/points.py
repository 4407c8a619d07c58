"""Line matches -> pixel pairs and midpoint-triangulated points.

A match is a line-1 sample (flat index ``i`` into the samples of
:class:`sefm_recon.geometry.epipolar.LinePairs`) and its partner's position
``j[i]`` along line 2, in samples from the line's start (NaN: none). The
validity checks (:mod:`.validity`), the search bands of propagation
(:mod:`.propagate`) and the output need the pixels and the 3-D point of each.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..geometry.epipolar import LinePairs
from ..geometry.triangulate import points_at_distance, ray_midpoint
from ..geometry.two_view import TwoView


class PairGeometry(NamedTuple):
    """Where the samples of both lines of every pair lie, and the cameras (the point kernels' geometry)."""

    start1: np.ndarray  #: (L, 2) float64, sample 0 of each line 1, COLMAP pixels
    step1: np.ndarray  #: (L, 2) float64, from one sample to the next
    off1: np.ndarray  #: (L + 1,) int64, line 1's samples in the flat arrays
    start2: np.ndarray  #: (L, 2) float64, the same for line 2
    step2: np.ndarray  #: (L, 2) float64
    Kinv1: np.ndarray  #: (3, 3) inverse intrinsics of camera 1
    Kinv2: np.ndarray  #: (3, 3) of camera 2
    Rt: np.ndarray  #: (3, 3) ``R^T``: camera-2 rays into camera-1 axes
    c2: np.ndarray  #: (3,) camera 2's centre in camera 1's frame


class LinePoints(NamedTuple):
    """The matched samples as pixel pairs and points, in line order (:func:`line_matches_to_points`)."""

    idx: np.ndarray  #: (M,) int64 flat sample index
    line: np.ndarray  #: (M,) int64 line pair
    uv1: np.ndarray  #: (M, 2) COLMAP pixels in image 1
    uv2: np.ndarray  #: (M, 2) in image 2; (0, 2) when not asked for
    X: np.ndarray  #: (M, 3) midpoint, camera-1 frame; (0, 3) when not asked for
    dist: np.ndarray  #: (M,) distance from camera 1
    valid: np.ndarray  #: (M,) bool: finite, in front of both cameras, wide enough an angle


class SamplePair(NamedTuple):
    """One match's pixels, point, distance and validity (:func:`_sample_pair`)."""

    x1: float
    y1: float
    x2: float
    y2: float
    x: float  #: the point, camera-1 frame
    y: float
    z: float
    dist: float
    ok: bool


def pair_geometry(lp: LinePairs, tv: TwoView) -> PairGeometry:
    """The :class:`PairGeometry` of this pair's line samples and cameras."""
    Rt = np.ascontiguousarray(tv.R.T)
    start1, step1, off1 = lp.side(1)
    start2, step2, _ = lp.side(2)
    return PairGeometry(start1, step1, off1, start2, step2, np.linalg.inv(tv.K1), np.linalg.inv(tv.K2), Rt,
                        -Rt @ np.asarray(tv.t, np.float64))


@njit(inline="always")
def _sample_pair(l, k, jj, geo, cos_max):
    """Sample ``k`` of line ``l`` and its partner ``jj``: the :class:`SamplePair` (``cos_max``: of the least angle)."""
    x1 = geo.start1[l, 0] + k * geo.step1[l, 0]
    y1 = geo.start1[l, 1] + k * geo.step1[l, 1]
    x2 = geo.start2[l, 0] + jj * geo.step2[l, 0]
    y2 = geo.start2[l, 1] + jj * geo.step2[l, 1]
    m = ray_midpoint(geo.Kinv1, geo.Kinv2, geo.Rt, geo.c2, x1, y1, x2, y2)
    d = np.sqrt(m.x * m.x + m.y * m.y + m.z * m.z)
    ok = 1.0 - m.cos * m.cos > 1e-12 and m.s1 > 0 and m.s2 > 0 and np.isfinite(d) and m.cos <= cos_max
    return SamplePair(x1, y1, x2, y2, m.x, m.y, m.z, d, ok)


@njit(parallel=True, cache=True)
def line_matches_to_points(j, cost, max_cost, geo, min_angle, pairs=True):
    """Matched samples -> pixel pairs and midpoint-triangulated points, in line order.

    Sample ``i`` of line ``l`` (flat index ``off1[l] + i``) with a finite partner
    position ``j`` (N1,) on line 2 and ``cost`` (N1,) at most ``max_cost`` becomes the pair
    ``start1[l] + i step1[l]``, ``start2[l] + j step2[l]`` (``geo``, a
    :class:`PairGeometry`); see :func:`sefm_recon.geometry.triangulate.triangulate`
    for the geometry. A point is valid when seen under ``min_angle`` radians or more.

    Returns the :class:`LinePoints` of the M matches. With ``pairs`` False,
    ``uv2`` and ``X`` are empty: callers that need only the depths skip
    writing (and faulting in) 40 bytes a match.
    """
    off1 = geo.off1
    L = off1.shape[0] - 1
    count = np.zeros(L + 1, np.int64)
    for ll in prange(L):
        l = np.int64(ll)
        c = 0
        for i in range(off1[l], off1[l + 1]):
            if np.isfinite(j[i]) and cost[i] <= max_cost:
                c += 1
        count[l + 1] = c
    pos = np.cumsum(count)
    M = pos[L]
    idx = np.empty(M, np.int64)
    line = np.empty(M, np.int64)
    uv1 = np.empty((M, 2))
    P = M if pairs else 0
    uv2 = np.empty((P, 2))
    X = np.empty((P, 3))
    dist = np.empty(M)
    valid = np.empty(M, np.bool_)
    cos_max = np.cos(min_angle)
    for ll in prange(L):
        l = np.int64(ll)
        p = pos[l]
        for i in range(off1[l], off1[l + 1]):
            if not (np.isfinite(j[i]) and cost[i] <= max_cost):
                continue
            s = _sample_pair(l, i - off1[l], j[i], geo, cos_max)
            idx[p] = i
            line[p] = l
            uv1[p, 0] = s.x1
            uv1[p, 1] = s.y1
            if pairs:
                uv2[p, 0] = s.x2
                uv2[p, 1] = s.y2
                X[p, 0] = s.x
                X[p, 1] = s.y
                X[p, 2] = s.z
            dist[p] = s.dist
            valid[p] = s.ok
            p += 1
    return LinePoints(idx, line, uv1, uv2, X, dist, valid)


@njit(parallel=True, cache=True)
def sample_points(samples, line, j, geo, min_angle):
    """:func:`line_matches_to_points` for the listed samples only: ``uv1`` (M, 2), ``dist`` (M,), ``valid`` (M,).

    ``samples`` (M,) flat sample indices with finite ``j``, ``line`` (M,) their lines.
    """
    M = samples.shape[0]
    uv1 = np.empty((M, 2))
    dist = np.empty(M)
    valid = np.empty(M, np.bool_)
    cos_max = np.cos(min_angle)
    for p in prange(M):
        i = samples[p]
        l = line[p]
        s = _sample_pair(l, i - geo.off1[l], j[i], geo, cos_max)
        uv1[p, 0] = s.x1
        uv1[p, 1] = s.y1
        dist[p] = s.dist
        valid[p] = s.ok
    return uv1, dist, valid


def line_points(j: np.ndarray, cost: np.ndarray, max_cost: float, min_angle: float, lp: LinePairs, tv: TwoView,
                pairs: bool = True) -> LinePoints:
    """:func:`line_matches_to_points` with this pair's line geometry and cameras (``min_angle`` radians)."""
    return line_matches_to_points(j, cost, max_cost, pair_geometry(lp, tv), min_angle, pairs)


def points_of_samples(samples: np.ndarray, j: np.ndarray, lp: LinePairs, tv: TwoView):
    """:func:`line_points` (no angle limit) of the listed samples (M,): ``uv1`` (M, 2), ``dist``, ``valid`` (M,)."""
    line = np.searchsorted(lp.offset1, samples, side="right") - 1
    return sample_points(samples, line, j, pair_geometry(lp, tv), 0.0)


def at_distance(uv1: np.ndarray, dist: np.ndarray, tv: TwoView) -> tuple[np.ndarray, np.ndarray]:
    """Points at ``dist`` (N,) along the rays of ``uv1`` (N, 2) and their partners on the epipolar lines.

    Returns ``X`` (N, 3) camera-1 frame and ``uv2`` (N, 2) COLMAP pixels.
    """
    f64 = lambda a: np.ascontiguousarray(a, np.float64)  # noqa: E731
    return points_at_distance(f64(np.linalg.inv(tv.K1)), f64(tv.K2), f64(tv.R), f64(np.ravel(tv.t)),
                              f64(uv1), f64(dist))
