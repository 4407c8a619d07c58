"""Semi-global matching over the polar line images (``dense.method = "sgm"``).

The paper's DP along one epipolar line (§4.4) is the single-path case of
semi-global matching over the rows of the line images (:mod:`.lines`). Here OpenCV's
StereoSGBM aggregates the cost along several paths across neighbouring lines, with
its Birchfield-Tomasi cost on gradient-prefiltered images (robust to gain and
offset), a uniqueness test, a left-right check and sub-pixel interpolation. The
search range comes from the parallax of the pose's SIFT inliers (:func:`search_range`).
Each valid disparity becomes a match through its two rays, one match per pixel of
image 1 (:func:`one_per_pixel`); points are triangulated as for SeFM's own matches.
"""

from __future__ import annotations

import logging
import math
import time

import cv2
import numpy as np

from ..config import Config
from ..errors import InputError
from ..geometry.epipolar import ray_angles
from ..geometry.triangulate import triangulate
from ..geometry.two_view import TwoView
from .lines import LineGrid, line_grid, line_images, pixel_grid, project, rays
from .sefm import DenseMatches

logger = logging.getLogger(__name__)

__all__ = ["match_pair_sgm", "parallax_columns"]

#: StereoSGBM's settings, those of the evaluation's planar SGBM peer: 5x5 blocks, OpenCV's
#: recommended smoothness penalties P1 = 8 C B^2 and P2 = 32 C B^2 (C channels),
#: uniqueness 10 %, speckle filter over windows of 100 px within 2 disparities, and
#: a left-right check within 1 disparity. (3x3 blocks gained 0.005-0.01 on the real pairs
#: but lost 0.02-0.09 on the noisier generated scenes.)
BLOCK = 5
UNIQUENESS = 10
SPECKLE_WINDOW = 100
SPECKLE_RANGE = 2
LR_MAX_DIFF = 1
#: Full 8-path aggregation (OpenCV's MODE_HH) keeps the whole cost volume, about 4 bytes a
#: cell: it is used up to this many cells (1 GB), the 3-direction mode (rows of the volume
#: only) above. On the real pairs 8 paths gave +0.015 precision and coverage at 1 px.
MAX_FULL_VOLUME = 250_000_000
#: The parallax of the SIFT inliers is searched widened by this share of its span on each
#: side (surfaces nearer or farther than every SIFT point), and by at least
#: ``MARGIN_COLUMNS``, the evaluation's SGBM peer's margin of 8 px.
RANGE_MARGIN = 0.25
MARGIN_COLUMNS = 8
#: SIFT depth ranges are sampled over image 1 on a grid this coarse (px).
_GRID_PX = 8.0


def parallax_columns(tv: TwoView, grid: LineGrid, size1: tuple[int, int], distances: tuple[float, float]):
    """(lo, hi) of the column difference ``column(alpha1) - column(alpha2)`` over image 1
    for scene points at the given distances from camera 1 (``inf`` allowed: no parallax)."""
    p = pixel_grid(*size1, _GRID_PX)
    r = np.column_stack([p, np.ones(len(p))]) @ np.linalg.inv(tv.K1).T
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    b = grid.basis[0]
    c2 = -tv.R.T @ tv.t
    a1 = np.arccos(np.clip(r @ b, -1.0, 1.0))
    out = []
    for dist in distances:
        if not np.isfinite(dist):
            out.append(np.zeros(1))
            continue
        d2 = r * dist - c2
        a2 = np.arccos(np.clip((d2 @ b) / np.linalg.norm(d2, axis=1), -1.0, 1.0))
        out.append(grid.column(a1) - grid.column(a2))
    d = np.concatenate(out)
    return float(d.min()), float(d.max())


def search_range(tv: TwoView, grid: LineGrid, size1: tuple[int, int]) -> tuple[float, float]:
    """(lo, hi) columns of parallax to search: the SIFT inliers' own column differences
    (1st-99th percentile), widened on each side by :data:`RANGE_MARGIN` of their span and
    at least :data:`MARGIN_COLUMNS`. With fewer than 8 inliers, all scene points from a
    fifth of the baseline to infinity.

    A margin in parallax rather than in depth: on the generated scenes the depth margin
    (x2 / 2) widened the search 2-4 fold and cost 0.09 of coverage at 1 px.
    """
    if len(tv.kp1) < 8:
        return parallax_columns(tv, grid, size1, (0.2 * float(np.linalg.norm(tv.t)), float("inf")))
    _, a1 = ray_angles(tv.K1, np.eye(3), grid.basis, tv.kp1)
    _, a2 = ray_angles(tv.K2, tv.R.T, grid.basis, tv.kp2)
    d = grid.column(a1) - grid.column(a2)
    lo, hi = np.percentile(d, [1, 99])
    m = max(MARGIN_COLUMNS, RANGE_MARGIN * (hi - lo))
    return float(lo - m), float(hi + m)


def one_per_pixel(uv1: np.ndarray, uv2: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Indices of the matches to keep so that each pixel of image 1 holds at most one.

    The line images sample an image around its epipole far more densely than its pixels
    (the rows fan out from it). Of the samples in one pixel, the one kept is the one whose
    displacement ``uv2 - uv1`` is nearest the mean displacement of them all: the
    consensus of its neighbours, not a chance sample.

    ``uv1``, ``uv2``: (N, 2) COLMAP positions; ``uv1`` inside an image of ``size`` = (width, height).
    """
    if len(uv1) == 0:
        return np.zeros(0, np.int64)
    ij = np.floor(uv1).astype(np.int64)
    pixel = ij[:, 1] * size[0] + ij[:, 0]
    order = np.argsort(pixel, kind="stable")
    p = pixel[order]
    starts = np.flatnonzero(np.r_[True, p[1:] != p[:-1]])
    flow = (uv2 - uv1)[order]
    counts = np.diff(np.r_[starts, len(p)])
    mean = np.add.reduceat(flow, starts, axis=0) / counts[:, None]
    group = np.repeat(np.arange(len(starts)), counts)
    dist = np.sum((flow - mean[group]) ** 2, axis=1)
    best = np.lexsort((dist, group))  # sorted by group, then by distance
    first = np.r_[True, group[best][1:] != group[best][:-1]]
    return np.sort(order[best[first]])


def match_pair_sgm(img1: np.ndarray, img2: np.ndarray, tv: TwoView, cfg: Config,
                   progress: bool = False) -> DenseMatches:
    """Dense matches between two working images by SGM on their polar line images.

    Args:
        img1, img2: (H, W, 3) uint8 RGB, undistorted, matching ``tv.K1``/``tv.K2``.
        tv: relative geometry.
        progress: accepted for the signature of :func:`.sefm.match_pair`; one OpenCV call
            shows no progress.
    Returns the matches in the working frame (``line`` = row of the line images).
    """
    timings = {}
    t0 = time.perf_counter()
    size1 = (img1.shape[1], img1.shape[0])
    size2 = (img2.shape[1], img2.shape[0])
    grid = line_grid(tv, size1, size2, cfg.lines.max_lines)
    if len(grid.phi) == 0:
        raise InputError("no epipolar line crosses both images: with this geometry the views do not overlap")
    lo, hi = search_range(tv, grid, size1)
    min_d = int(math.floor(lo - MARGIN_COLUMNS))
    num_d = int(math.ceil((hi - lo + 2 * MARGIN_COLUMNS + 1) / 16.0)) * 16  # OpenCV: a multiple of 16
    grid.pad = max(min_d + num_d, 0) + 1  # every column of image 1 keeps its whole search window
    width = grid.pad + grid.columns + max(-min_d, 0) + 1
    L1, L2 = line_images(img1, img2, tv, grid, width)
    timings["line_pairs"] = time.perf_counter() - t0
    logger.info("line images %dx%d, parallax %d..%d columns", width, len(grid.phi), min_d, min_d + num_d)

    t0 = time.perf_counter()
    cn = L1.shape[2] if L1.ndim == 3 else 1
    full = L1.shape[0] * L1.shape[1] * num_d <= MAX_FULL_VOLUME
    sgbm = cv2.StereoSGBM_create(minDisparity=min_d, numDisparities=num_d, blockSize=BLOCK,
                                 P1=8 * cn * BLOCK**2, P2=32 * cn * BLOCK**2, disp12MaxDiff=LR_MAX_DIFF,
                                 uniquenessRatio=UNIQUENESS, speckleWindowSize=SPECKLE_WINDOW,
                                 speckleRange=SPECKLE_RANGE,
                                 mode=cv2.STEREO_SGBM_MODE_HH if full else cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp = sgbm.compute(L1, L2).astype(np.float32) / 16.0  # fixed point, 4 fractional bits
    del L1, L2
    rows, cols = np.nonzero(disp >= min_d)
    d = disp[rows, cols].astype(np.float64)
    del disp
    n_dense = len(d)
    a1, a2 = grid.alpha(cols), grid.alpha(cols - d)
    ok = (a1 > 0) & (a2 < np.pi)
    phi = grid.phi[rows]
    u1, v1, f1 = project(tv.K1, np.eye(3), rays(grid.basis, phi, a1))
    u2, v2, f2 = project(tv.K2, tv.R.T, rays(grid.basis, phi, a2))
    with np.errstate(invalid="ignore"):
        ok &= f1 & f2 & (u1 >= 0) & (u1 < size1[0]) & (v1 >= 0) & (v1 < size1[1])
        ok &= (u2 >= 0) & (u2 < size2[0]) & (v2 >= 0) & (v2 < size2[1])
    uv1 = np.column_stack([u1[ok], v1[ok]])
    uv2 = np.column_stack([u2[ok], v2[ok]])
    rows = rows[ok]
    one = one_per_pixel(uv1, uv2, size1)
    uv1, uv2, rows = uv1[one], uv2[one], rows[one]
    X, valid, _ = triangulate(tv.K1, tv.K2, tv.R, tv.t, uv1, uv2)
    keep = np.flatnonzero(valid)
    timings["matching"] = time.perf_counter() - t0
    counts = {
        "line_pairs": int(len(grid.phi)),
        "samples": int(len(grid.phi) * grid.columns),
        "rough_matches": 0,
        "dense_matches": n_dense,
        "valid_matches": int(len(keep)),
    }
    logger.info("SGM (%s): %d line pairs, %d dense, %d valid", "8 paths" if full else "3 directions",
                counts["line_pairs"], n_dense, len(keep))
    return DenseMatches(uv1[keep], uv2[keep], np.ones(len(keep)), rows[keep], X[keep], counts, timings)
