"""Search bands: the line-2 samples that may hold each line-1 sample's partner.

A point at distance ``d`` from camera 1 along a line-1 sample's ray is seen
from camera 2 under a ray angle that falls as ``d`` grows, so a range of
distances is a range of line-2 samples (:func:`sefm_recon.geometry.kernels.depth_band`).
The range is the SIFT points' (:func:`.sefm.depth_range`) for the whole
image, or near each pixel the matches' of a coarser pyramid level
(:func:`coarse_search_band`) or of the neighbouring matches (:mod:`.propagate`),
kept as per-pixel min and max distance grids (:func:`depth_grids`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..geometry.epipolar import LinePairs, line_alphas
from ..geometry.kernels import depth_band
from ..geometry.kernels import invert_band as _invert_band
from ..geometry.kernels import rasterise_min_max
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
    :func:`sefm_recon.geometry.kernels.invert_band`.
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
