"""Semi-global matching over the polar line images (``dense.method = "sgm"``).

The paper's DP along one epipolar line (§4.4) is the single-path case of
semi-global matching over the rows of the line images (:mod:`.lines`). Here OpenCV's
StereoSGBM aggregates the cost along several paths across neighbouring lines, with
its Birchfield-Tomasi cost on gradient-prefiltered images (robust to gain and
offset), a uniqueness test, a left-right check and sub-pixel interpolation. The
search range of every pixel comes from the depths of the pose's SIFT inliers
(:func:`.sefm.depth_range`). Each valid disparity becomes a match through its two
rays; points are triangulated as for SeFM's own matches.
"""

from __future__ import annotations

import logging
import math
import time

import cv2
import numpy as np

from ..config import Config
from ..errors import InputError
from ..geometry.triangulate import triangulate
from ..geometry.two_view import TwoView
from .lines import LineGrid, line_grid, line_images, pixel_grid, project, rays
from .sefm import DenseMatches, depth_range

logger = logging.getLogger(__name__)

__all__ = ["match_pair_sgm", "parallax_columns"]

#: StereoSGBM's settings, those of the evaluation's planar SGBM peer: 5x5 blocks, OpenCV's
#: recommended smoothness penalties P1 = 8 C B^2 and P2 = 32 C B^2 (C channels),
#: uniqueness 10 %, speckle filter over windows of 100 px within 2 disparities, and
#: a left-right check within 1 disparity.
BLOCK = 5
UNIQUENESS = 10
SPECKLE_WINDOW = 100
SPECKLE_RANGE = 2
LR_MAX_DIFF = 1
#: Full 8-path aggregation (OpenCV's MODE_HH) keeps the whole cost volume, about 4 bytes a
#: cell: it is used up to this many cells (1 GB), the 3-direction mode (rows of the volume
#: only) above. On the real pairs 8 paths gave +0.015 precision and coverage at 1 px.
MAX_FULL_VOLUME = 250_000_000
#: Columns added on each side of the search range the SIFT depths give: the peer's ± 8 px.
MARGIN_COLUMNS = 8
#: SIFT depth ranges are sampled over image 1 on a grid this coarse (px).
_GRID_PX = 8.0


def parallax_columns(tv: TwoView, grid: LineGrid, size1: tuple[int, int], distances: tuple[float, float]):
    """(lo, hi) of ``(alpha2 - alpha1) / alpha_step`` over image 1 for scene points at the
    given distances from camera 1 (``inf`` allowed: no parallax)."""
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
        out.append((a2 - a1) / grid.alpha_step)
    d = np.concatenate(out)
    return float(d.min()), float(d.max())


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
    lo, hi = parallax_columns(tv, grid, size1, depth_range(tv, cfg.geometry.depth_margin))
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
    return DenseMatches(uv1[keep], uv2[keep], np.ones(len(keep)), rows[ok][keep], X[keep], counts, timings)
