"""Semi-global matching over the polar line images (``dense.method = "sgm"``).

The paper's DP along one epipolar line (§4.4) is the single-path case of
semi-global matching over the rows of the line images (:mod:`.lines`). Here OpenCV's
StereoSGBM aggregates the cost along several paths across neighbouring lines, with
its Birchfield-Tomasi cost on gradient-prefiltered images (robust to gain and
offset), a uniqueness test, a left-right check and sub-pixel interpolation, then a
median over each surface (:func:`surface_median`). The
search range comes from the parallax of the pose's SIFT inliers (:func:`search_range`),
extended towards the camera along the surfaces a coarse pass finds beyond them
(:func:`extend_near`);
estimates at its ends (:func:`drop_range_ends`), on windows reaching into an area
without signal (:func:`drop_flat_windows`) and on the plain strips a nearer surface
carries into an unmatched region (:func:`drop_occluded_plain`) are dropped, among others.
The disparities are then read back at every pixel of image 1 (:func:`pixel_matches`):
the pixel's own ray gives its row and column, the disparity there its ray in image 2,
so each pixel holds one match exactly on its epipolar line whatever the sampling of the
line images, and its scene point where the two rays meet; the holes of plain planes
are filled and their matches without signal moved onto them (:mod:`.planes`).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import cv2
import numpy as np
from numba import njit, prange

from ..arrays import append_rows, quiet_windows
from ..config import Config
from ..errors import InputError
from ..geometry.epipolar import ray_angles
from ..geometry.epipolar import pixel_ray
from ..geometry.two_view import TwoView
from ..io.images import to_gray
from .lines import LineGrid, line_grid, line_images, pixel_grid, project_polar
from .planes import fill_planes
from .sefm import DenseMatches, depth_range
from .zncc import zncc

logger = logging.getLogger(__name__)

__all__ = ["choose_jump_penalty", "coarse_parallax", "coarse_range", "CoarseParallax", "drop_carried_plain",
           "drop_collisions", "drop_fattened_cells", "drop_flat_windows", "drop_frame_end_runs", "drop_left_right",
           "drop_occluded_plain",
           "drop_off_half_size", "drop_outside_windows", "drop_range_ends", "drop_unanchored_far", "drop_unseen_far",
           "drop_unsupported_near", "every_parallax", "extend_near", "fill_from_half_size",
           "fit_plain_surfaces", "flat_windows", "half_size_sgm", "halve_line_images", "jump_ladder",
           "match_pair_sgm", "parallax_columns", "pixel_matches", "plain_windows", "search_range",
           "sift_parallax_columns", "speckle_window", "surface_median", "widen_range"]

#: StereoSGBM's settings, those of the evaluation's planar SGBM peer: 5x5 blocks, OpenCV's
#: recommended smoothness penalties P1 = 8 C B^2 and P2 = 32 C B^2 (C channels; the
#: multiples of C B^2 below), a speckle filter over windows of at least 100 px within 2
#: disparities (:data:`SPECKLE_SHARE`), and a left-right check within 1 disparity
#: (:data:`LR_MAX_DIFF`: OpenCV's own check, ``disp12MaxDiff``, changes no pixel in this
#: build; ours is :func:`drop_left_right`); the uniqueness margin and the switches of the
#: ablation are in ``cfg.sgm``. (3x3 blocks gained 0.005-0.01 on the real pairs but lost
#: 0.02-0.09 on the noisier generated scenes.)
BLOCK = 5
SPECKLE_WINDOW = 100
SPECKLE_RANGE = 2
LR_MAX_DIFF = 1
#: The speckle filter's window is at least this share of the cells SGM estimates (rows x
#: columns less the columns searched), at every size SGM runs: a patch of one surface cut
#: from all around it by jumps or gaps and smaller than 1/500 of the view is more often a
#: wrong minimum than a surface (a periodic floor matched a period off, a zoomed floor near
#: image 2's edge matched at a farther depth). The peer's 100 px alone keep islands of 1/7500
#: of a 1000x750 view. Against them (true pose, p@1 / p@3 / cov@1): generated 0.927 / 0.980 /
#: 0.706 -> 0.935 / 0.985 / 0.702, every seed more precise (the zoom seeds 11 and 15 from 0.953
#: and 0.959 to 0.976 and 0.974 at 3 px); real 0.953 / 0.974 / 0.885 -> 0.954 / 0.975 / 0.883
#: (Midd1's plain wall, matched in small patches, -0.01 to -0.02 of coverage). At 1/1000
#: (windows over the whole width): generated 0.933 / 0.985 / 0.703, real 0.953 / 0.975 / 0.884,
#: most of the precision for half the coverage; 1/500 is kept for the gross errors at 3 px, the
#: goal missed most.
#: A fixed window sized for 1000x750 views is too large for the real pairs' third-size views
#: (1600 px: Midd1 conv 0.679 -> 0.517 of coverage).
SPECKLE_SHARE = 0.002
#: The left-right check's second SGM (from image 2 to image 1) runs on copies of the line
#: images reduced this many times on both axes, its tolerance :data:`LR_MAX_DIFF` columns
#: there. At half size it costs an eighth of the first (0.24 s on the bench pair) and judges
#: better than at full size: its windows see twice the texture and half the sensor noise.
#: Measured (true pose, p@1 / p@3 / cov@1, against no check): generated 0.9027 / 0.9636 /
#: 0.6537 -> 0.9229 / 0.9798 / 0.6501 at half size, 0.9189 / 0.9757 / 0.6376 at full size;
#: real 0.9520 / 0.9734 / 0.8804 -> 0.9542 / 0.9751 / 0.8746 and 0.9562 / 0.9763 / 0.8788
#: (the small real pairs, 384-700 px wide, lose the most at half size: thin structures and
#: specks of the plain walls take their surroundings' parallax there). A reduced row averages
#: two lines: a surface whose parallax changes by a column or more from one line to the next
#: mixes there (a floor at a column a line keeps 78 % of its matches instead of 96 %; at
#: half a column every one). Reduced along the lines only, it keeps such a floor: real
#: 0.9548 / 0.9756 / 0.8773, generated 0.9205 / 0.9780 / 0.6485 (zoom 0.969 at 3 px), at
#: twice the cost (0.50 s on the bench pair against 0.24 s).
LR_REDUCTION = 2
#: The half-size fill (:func:`fill_from_half_size`) takes a halved cell's estimate only where
#: the derivative along the line of its window (:data:`FILL_WINDOW` halved cells square, the
#: horizontal Sobel that SGM's cost sees) correlates with its partner's by at least this:
#: r^2 >= 1/2, half of the window's derivative energy shared with the partner. A shaded
#: plain surface (a ramp: a constant derivative, sensor noise about it) correlates near 0
#: at every parallax, a texture of low contrast near 1 at its own. Measured (true pose,
#: p@1 / p@3 / cov@1, against no fill: generated 0.9229 / 0.9798 / 0.6501, real 0.9543 /
#: 0.9751 / 0.8746): at r^2 >= 1/2 generated 0.9219 / 0.9796 / 0.6875, real 0.9525 /
#: 0.9738 / 0.8755; at r >= 0.5 0.9197 / 0.9787 / 0.7014 and 0.9515 / 0.9732 / 0.8766;
#: without the test 0.9067 / 0.9716 / 0.7128 and 0.9447 / 0.9683 / 0.8835 (generated
#: seed 16's shaded sphere and the real Plastic's plain walls filled wrong).
FILL_MIN_ZNCC = math.sqrt(0.5)
#: ...over 7x7 halved cells (14x14 pixels): enough samples that noise alone rarely
#: correlates by 0.7 (its spread about 0.15, one over the square root of 49, somewhat more
#: as the Sobel correlates neighbouring cells), yet local enough for a slanted surface.
FILL_WINDOW = 7
#: Coarse to fine both ways (:func:`drop_off_half_size`): a full-size estimate more than this
#: many columns from the half-size SGM's, where that one is sure, is dropped (the fill then
#: gives it the reduced estimate where that passes its own test). The reduced estimate holds
#: to a reduced column (two full ones, the spread its four cells may have), and one more
#: for the full-size run's own sub-column error: beyond that the two levels found different
#: surfaces.
HALF_CHECK_COLUMNS = 3.0
#: ...sure: every reduced cell of the square this many reduced cells across about the cell
#: holds an estimate, within :data:`HALF_CHECK_SPREAD` reduced columns of each other. The
#: reduced windows (:data:`BLOCK` reduced cells, twice the full-size ones on the scene)
#: fatten a nearer surface up to half a window beyond its edge; asked of the four reduced
#: cells about the cell alone, the check dropped the right full-size estimates just beyond
#: each depth edge (every real pair -0.002 to -0.005 of coverage).
HALF_CHECK_SQUARE = BLOCK
#: ...this spread over the square: a slanted surface's parallax changes by a column or two
#: across it (generated seed 5's floor; within one, seed 5 0.969 at 3 px against 0.971
#: within two), a depth edge the check must not judge, by more. Measured (true pose, p@1 /
#: p@3 / cov@1, against none: real 0.9525 / 0.9738 / 0.8755, generated 0.9219 / 0.9796 /
#: 0.6875): real 0.9525 / 0.9740 / 0.8754, generated 0.9219 / 0.9800 / 0.6908.
HALF_CHECK_SPREAD = 2.0
STEP_PENALTY = 8
JUMP_PENALTY = 32
#: The jump penalty P2 is chosen per pair (:func:`choose_jump_penalty`): from OpenCV's 32 it
#: doubles or halves while that keeps more cells through SGM's own checks (uniqueness,
#: left-right, speckle, windows without signal, ends of the search), the penalty whose
#: disparities agree with themselves best. The real pairs and the generated scenes want
#: opposite smoothing: fixed at 16 the plain walls of Midd1 and Midd2 gain 0.04-0.08 of
#: precision and 0.06-0.10 of coverage at 1 px and the generated scenes lose 0.03 / 0.09;
#: fixed at 64 the generated scenes gain 0.02 / 0.05 and the real pairs lose 0.004 / 0.009
#: (results.md). Between :data:`STEP_PENALTY` (a jump no dearer than a step of one
#: disparity) and four times OpenCV's.
JUMP_MIN, JUMP_MAX = STEP_PENALTY, 4 * JUMP_PENALTY
#: A step is taken where it keeps more than this share more cells: on the textured real pairs
#: (Cloth, Baby, Rocks), where no penalty stands out, the halved copies' counts at 16 and 64
#: lie a median 0.4 % from 32's (at most 1.25 %, none of them more than 1 % above it); Midd1's
#: and Midd2's at 16 lie 1.5-12 % above, the generated scenes' at 64 up to 12 %. Margins of
#: 0.5 % and 2 % measured worse on both families (results.md).
JUMP_MARGIN = 0.01
#: The cells are counted on copies of the line images reduced by this factor on both axes:
#: an eighth of the cost volume (the three runs took 0.38 s on the bench pair, 45 % of its
#: full-size SGM). At 1/4 the counts no longer tell the walls apart (Midd1 and Midd2 got 64),
#: so the quarter-size copies only say where the penalty does not matter: where half and
#: twice 32 keep the same cells within the margin there, 32 stays without the half-size
#: runs (41 of the 60 real cases, the bench pair: 0.38 -> 0.1 s; no generated scene; of the
#: 41, only Monopoly rect and conv would have stepped at half size, to 128 and 64, which
#: lose 0.001-0.007 of precision and 0.002-0.006 of coverage at 1 px there).
CHOICE_REDUCTION = 2
#: Aggregation over the whole cost volume (OpenCV's MODE_HH4: four full paths, along the
#: lines both ways and across them both ways) keeps the volume, about 4 bytes a cell: it
#: is used up to this many cells (1 GB), the 3-direction mode (rows of the volume only)
#: above. OpenCV's 8-path mode (MODE_HH) adds the diagonals, and near the top and bottom
#: of the line images they outvote the paths along the lines: a slanted floor in the
#: last 16 rows of Midd1 took the depth of the surface above it, none of it within 1 px.
#: Over the 60 real cases the four paths gave +0.006 precision and +0.010 coverage at
#: 1 px against the eight (the generated scenes: -0.003 / +0.001), in half the time.
MAX_FULL_VOLUME = 250_000_000
#: The parallax range (the SIFT inliers' 1st to 99th percentile) is widened by this many
#: columns on each side, the evaluation's SGBM peer's margin of 8 px (``cfg.sgm.range_margin``
#: can add a share of the range's span). A quarter span more on each side, the default
#: before, searched 1.35 times the columns on the bench pair (0.3 s of SGM) for nothing:
#: real pairs 0.9152 / 0.8803 at 1 px without it against 0.9152 / 0.8805 with it, the
#: generated scenes 0.793 / 0.584 against 0.786 / 0.576 (fewer far candidates, fewer wrong
#: minima on plain surfaces).
MARGIN_COLUMNS = 8
#: The search then goes this many columns further at each end (OpenCV's estimates at the
#: ends of its range are poor), and one more: an estimate within one column of either end
#: of the search (``cfg.sgm.end_check``) is dropped. Its cost has no neighbour beyond it,
#: so its minimum is the edge of the search, not a minimum found; and it is where OpenCV
#: breaks the ties of a plain surface (the first disparity of the search wins: the plain
#: walls of Midd2 and Monopoly, 40 % of their matches, lay there, up to 8 px from their
#: true depth). Measured at 1 px on the real pairs: +0.029 precision, coverage within
#: 0.001 (the ablation); on the generated scenes, with line images 0.8 px apart, +0.047
#: / -0.002.
END_COLUMNS = 8
#: Without SIFT points to bound the search (fewer than 8 inliers), a coarse pass
#: (:func:`coarse_range`) matches copies of the images reduced by a power of two (at
#: least 2) until their line images are at most this many columns wide, over every
#: parallax from :data:`NEAR_BASELINES` to infinity, and the full-size search spans what
#: it found. (The dino's pairs two views apart searched up to 10,800 columns, 2.7 s a
#: call, and 8 of 16 gave no point; with the pass, 2-4 s and all 16 give points.)
COARSE_COLUMNS = 384
#: ...between these percentiles of its disparities, so that a few stray matches do not
#: widen it.
COARSE_PERCENTILES = (0.5, 99.5)
#: The nearest scene point searched without SIFT points: a fifth of the baseline from
#: camera 1 (as the DP's depth band, :func:`.sefm.depth_range`).
NEAR_BASELINES = 0.2
#: The coarse pass that extends the SIFT range towards the camera (:func:`extend_near`)
#: searches from the SIFT range's far end to the parallax of half the distance of the
#: nearest SIFT points (their 1st percentile) anywhere in image 1, the bound of the
#: depth-halved search (``cfg.sgm.sift_range = false``). Against every parallax up to
#: :data:`NEAR_BASELINES`: the same extension on all 20 generated seeds, the coarse pass
#: 0.055 s instead of 0.195 s on the bench pair (112 coarse columns searched, not 780).
NEAR_DEPTH = 2.0
#: SIFT depth ranges are sampled over image 1 on a grid this coarse (px).
_GRID_PX = 8.0
#: Neighbouring disparities within this many columns of the nearest cell's are on its
#: surface and are interpolated with it; others (across a depth edge) are left out. One
#: column is the left-right check's own tolerance (:data:`LR_MAX_DIFF`).
SAME_SURFACE_COLUMNS = 1.0
#: The disparities are smoothed by a median over each 5x5 window of the line images (OpenCV's
#: medianBlur, its largest window for floats), applied this many times, as Hirschmueller's SGM
#: filters its disparity image: on noisy and weakly textured surfaces the winner of the
#: aggregation scatters by a column or two about the surface (Plastic: 0.80 of its matches
#: within 1 px, 0.92 within 3 px). Measured at 1 px against none (precision / coverage): one
#: pass, real pairs +0.001 / +0.001 (generated scenes +0.006 / +0.003 with the rejected cells
#: voting at their invalid value); two passes, generated +0.008 / +0.006 and real +0.002 /
#: +0.001; three +0.009 / +0.007 on the generated scenes. A 9x9 window of
#: exact medians gave +0.011 / +0.008 and +0.002 / +0.001 but took 2 s on the bench pair (0.3 s
#: as a row pass then a column pass, +0.008 / +0.006); a 17x17 window lost 0.02 of precision
#: on the converging scenes.
MEDIAN_PASSES = 2
#: A cell takes its window's median only where that lies within this many columns of its
#: own estimate: on its surface (the errors the median corrects lie within 1-3 columns); across
#: a depth edge the window's majority is the other surface, and the cell keeps its estimate.
MEDIAN_SAME_SURFACE = 3.0
#: The median is taken about the window's plane (:func:`surface_median`) where the
#: disparities of the cell's (2 :data:`PLAIN_FIT_HALF` + 1)-cell window lie within this many
#: columns (root mean square) of their least-squares plane. A step of h columns inside the
#: window leaves 0.25 h to 0.29 h about the plane, so windows with a step of 2 columns or
#: more keep the plain median, which keeps steps sharp; smaller steps the median treats as
#: one surface anyway (:data:`MEDIAN_SAME_SURFACE`). Measured (p@1 / p@3 / cov@1, true pose;
#: plain median 0.9535 / 0.9749 / 0.8829 real, 0.9345 / 0.9851 / 0.7017 generated): 0.5
#: gave 0.9540 / 0.9749 / 0.8830 and 0.9359 / 0.9852 / 0.7027; 1.0, which lets steps of 3
#: columns in, 0.9536 / 0.9754 / 0.8827 and 0.9374 / 0.9854 / 0.7038, with tsukuba, Baby3
#: and Cloth3 0.002-0.003 less precise.
PLANE_RMS = 0.5
#: ...and where at least this many of its cells are valid (a plane needs a few more than three).
PLANE_MIN_CELLS = 6
#: ...and where that plane slopes by at least this many columns a cell along or across the
#: lines: a tenth of a column a cell moves the 5x5 window's edge cells by 0.2 columns, a
#: fifth of the 1 px that a match is judged by; flatter windows keep the plain median (the
#: generated scenes 0.9359 / 0.7027 -> 0.9367 / 0.7035 at 1 px, seeds 4, 10 and 15 no
#: longer 0.002-0.004 less precise than with the plain median; the real pairs the same).
MEDIAN_MIN_SLOPE = 0.1
#: Rows of :func:`local_planes` a thread takes in turn (the window's column sums slide down
#: them, a row in and a row out; the first of each block sums its window afresh).
PLANE_ROWS_A_BLOCK = 32
#: On plain windows the cost hardly changes from one disparity to the next, and SGM's winner
#: is set by its smoothness penalties: a slanted plain surface comes out as a staircase of
#: fronto-parallel steps that the median keeps (Plastic's box face: 21 % of its matches
#: 1-3 px off). There each disparity is replaced by the plane fitted (least squares) to the
#: disparities of its window on its surface (within :data:`MEDIAN_SAME_SURFACE` columns),
#: the first-order counterpart of the median, which textured windows keep: their winners
#: are the data's own (fine texture: median error 0.16 px), and a fit would round off
#: their relief (tsukuba and Cloth2 lost 0.007-0.009 of precision at 1 px with the fit
#: everywhere). A window is plain where the standard deviation of line image 1's grey
#: values over its :data:`BLOCK` square is below this many grey levels: the sensor noise of
#: a few grey levels and little more, where a shift of one column changes the cost by about
#: what the noise does. Measured (p@1 / cov@1, true pose): below 3, 6 and 12 grey levels and
#: everywhere, the real pairs 0.9351 / 0.8834, 0.9351 / 0.8834, 0.9347 / 0.8831 and 0.9333 /
#: 0.8823 (their fine textures lose beyond 6); the noisier generated scenes 0.8337 / 0.6348,
#: 0.8364 / 0.6370, 0.8390 / 0.6389 and 0.8413 / 0.6404. The largest level that costs the
#: real pairs nothing.
PLAIN_LEVELS = 6.0
#: The fit's window: (2 x this + 1) cells square. 9x9, 11x11 and 15x15 gave the same
#: means within 0.0002 in the prototype; the smallest of them costs the least (its cells
#: are summed for every plain cell).
PLAIN_FIT_HALF = 4
#: ...fitted where at least this share of the window's cells lies on the cell's surface: about
#: one quadrant of the window with the cell at its corner (25 of 81 cells), as a surface that
#: meets a depth edge or a hole at the cell still holds; fewer cells would fix a plane on a
#: sliver.
PLAIN_FIT_SUPPORT = 0.3
#: The confidence (``DenseMatches.score``) of a match filled from a plane (:mod:`.planes`): below
#: SGM's own (1), so that the pose check tracks the matches SGM found first.
PLANE_SCORE = 0.5
#: Pixels of image 1 read back at a time: bounds the per-pixel arrays to about 100 MB.
_CHUNK_PIXELS = 1 << 20


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


def search_range(tv: TwoView, grid: LineGrid, size1: tuple[int, int], margin: float = 0.0,
                 sift_parallax: bool = True) -> tuple[float, float]:
    """(lo, hi) columns of parallax to search: the SIFT inliers' own column differences
    (:func:`sift_parallax_columns`), widened on each side by ``margin`` of their span and at least
    :data:`MARGIN_COLUMNS`. With fewer than 8 inliers, all scene points from a fifth of
    the baseline to infinity (:func:`every_parallax`). Every range is then widened by
    :data:`END_COLUMNS` and one column more (whose estimates are dropped,
    :func:`drop_range_ends`).

    A margin in parallax rather than in depth (``sift_parallax=False``: the parallax of
    the SIFT points' depths, halved and doubled): the depth margin widens the search 2-4
    fold on the generated scenes.
    """
    if len(tv.kp1) < 8:
        return every_parallax(tv, grid, size1)
    if not sift_parallax:
        lo, hi = parallax_columns(tv, grid, size1, depth_range(tv, 2.0))
        return float(lo - END_COLUMNS - 1), float(hi + END_COLUMNS + 1)
    return widen_range(*sift_parallax_columns(tv, grid), margin)


def every_parallax(tv: TwoView, grid: LineGrid, size1: tuple[int, int]) -> tuple[float, float]:
    """(lo, hi) columns of parallax to search for every scene point seen in image 1 from
    :data:`NEAR_BASELINES` baselines to infinity, widened by :data:`END_COLUMNS` and one
    column more at each end."""
    lo, hi = parallax_columns(tv, grid, size1, (NEAR_BASELINES * float(np.linalg.norm(tv.t)), float("inf")))
    return float(lo - END_COLUMNS - 1), float(hi + END_COLUMNS + 1)


def sift_parallax_columns(tv: TwoView, grid: LineGrid) -> tuple[float, float]:
    """(lo, hi) columns of parallax of the SIFT inliers (``tv.kp1``/``tv.kp2``, at least
    one): their 1st and 99th percentiles, so that a stray inlier does not widen them."""
    _, a1 = ray_angles(tv.K1, np.eye(3), grid.basis, tv.kp1)
    _, a2 = ray_angles(tv.K2, tv.R.T, grid.basis, tv.kp2)
    lo, hi = np.percentile(grid.column(a1) - grid.column(a2), [1, 99])
    return float(lo), float(hi)


def widen_range(lo: float, hi: float, margin: float) -> tuple[float, float]:
    """A parallax range found (SIFT inliers, or the coarse pass) widened into the search: by
    ``margin`` of its span and at least :data:`MARGIN_COLUMNS` on each side, then by
    :data:`END_COLUMNS` and one column more (whose estimates are dropped, :func:`drop_range_ends`)."""
    m = max(MARGIN_COLUMNS, margin * (hi - lo))
    return float(lo - m - END_COLUMNS - 1), float(hi + m + END_COLUMNS + 1)


def drop_range_ends(disp: np.ndarray, lo: int, hi: int, invalid: float) -> int:
    """Set the disparities within one column of either end of the searched columns
    ``lo..hi`` to ``invalid``, in place; returns how many."""
    ends = (disp > invalid) & ((disp < lo + 1) | (disp > hi - 1))
    disp[ends] = invalid
    return int(np.count_nonzero(ends))


#: At a depth edge SGM's windows (:data:`BLOCK` columns) straddle both surfaces and the
#: nearer one, whose texture usually dominates, takes cells of the farther one: its
#: disparity runs past the edge ("fattening"), and the left-right check passes them, as both
#: directions fatten alike. The cells of the nearer side next to a jump of more than twice
#: the check's tolerance (:data:`LR_MAX_DIFF`) are dropped, this many: a window two
#: columns off the edge (BLOCK // 2) already holds more of its own surface. Measured on
#: the 60 real cases and 20 seeds (docs/results.md): 1 cell +0.005 of precision and
#: -0.003 of coverage at 1 px on both; 2 cells doubled the precision gain at 2.3 times
#: the coverage loss (Bowling2 rect 0.030 behind SGBM's coverage).
FATTENED_CELLS = 1


def drop_fattened_cells(disp: np.ndarray, invalid: float) -> int:
    """Set the :data:`FATTENED_CELLS` cells of the nearer (larger-parallax) side at each depth
    edge along the rows of ``disp`` to ``invalid``, in place; returns how many.

    A depth edge lies between two valid cells of a row whose disparities differ by more
    than ``2 * LR_MAX_DIFF`` columns, next to each other or across invalid cells no wider
    than that difference (plus the check's tolerance): the strip of the farther surface
    that the nearer one hides in image 2 is as wide as their parallax difference.
    """
    return int(_drop_fattened(disp, float(invalid), FATTENED_CELLS, 2.0 * LR_MAX_DIFF, float(LR_MAX_DIFF)).sum())


#: Two cells of a row on different surfaces (parallax more than ``2 * LR_MAX_DIFF`` apart)
#: whose matches fall within a pixel of each other in image 2 cannot both be seen there:
#: the nearer surface hides the farther one, or the nearer estimate is wrong (fattened past
#: a depth edge, a false minimum). The cell whose colour differs more from image 2's there
#: (the mean absolute difference over :data:`COLLISION_ROWS` rows and the channels) is
#: dropped, where it differs by more than this many grey levels: within one level the
#: 8-bit images cannot tell them apart, and both are kept. Measured against none: real
#: pairs +0.004 precision, -0.001 coverage at 1 px (p@3 +0.003), generated +0.003 / -0.002
#: (results.md); without the margin the same precision for more coverage lost, at 4 levels
#: (32 in the sum) half the precision.
COLLISION_LEVELS = 1.0
#: The rows compared (the cell's and one on each side): the neighbouring epipolar lines
#: cross an occlusion edge alike, and three rows halve the noise of one (five: the same).
COLLISION_ROWS = 3


def drop_collisions(disp: np.ndarray, L1: np.ndarray, L2: np.ndarray, shift: int, invalid: float) -> int:
    """Of each two cells of a row of ``disp`` on different surfaces whose matches land within
    one column of each other in line image 2, set the one whose colour differs more from
    image 2's there to ``invalid`` (:data:`COLLISION_LEVELS`), in place; returns how many.

    ``disp`` (rows, width) float32 parallax in columns, invalid at or below ``invalid``;
    ``L1``, ``L2`` (rows, width[, channels]) the line images SGM matched, image 2's shifted
    by ``shift`` columns (a cell ``c`` of parallax ``d`` matches ``c - (d - shift)`` in ``L2``).
    """
    a = L1 if L1.ndim == 3 else L1[:, :, None]
    b = L2 if L2.ndim == 3 else L2[:, :, None]
    return int(_drop_collisions(disp, a, b, float(shift), float(invalid), 2.0 * LR_MAX_DIFF, COLLISION_LEVELS,
                                COLLISION_ROWS // 2).sum())


@njit(cache=True)
def _colour_difference(L1, L2, r, c, p, half):
    """Mean |L1 - L2| over rows ``r - half .. r + half`` and the channels, between column ``c``
    of ``L1`` and fractional column ``p`` of ``L2`` (linear); infinite where ``p`` leaves it."""
    rows, width, cn = L1.shape
    p0 = int(np.floor(p))
    f = p - p0
    if p0 < 0 or p0 + 1 >= width:
        return np.inf
    s = 0.0
    n = 0
    for rr in range(max(r - half, 0), min(r + half + 1, rows)):
        for k in range(cn):
            s += abs(float(L1[rr, c, k]) - ((1.0 - f) * L2[rr, p0, k] + f * L2[rr, p0 + 1, k]))
            n += 1
    return s / n


@njit(parallel=True, cache=True)
def _drop_collisions(disp, L1, L2, shift, invalid, jump, margin, half):
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        row = disp[r]
        owner = np.full(width, -1, np.int64)  # per column of L2: the last cell kept that reached it
        drop = np.zeros(width, np.bool_)
        for c in range(width):
            if row[c] <= invalid:
                continue
            p = c - (row[c] - shift)
            b = int(np.floor(p + 0.5))
            if b < 0 or b >= width:
                continue
            for bb in range(max(b - 1, 0), min(b + 2, width)):
                o = owner[bb]
                if o < 0 or drop[o] or abs(row[o] - row[c]) <= jump:
                    continue  # none, or the same surface
                po = o - (row[o] - shift)
                if abs(po - p) >= 1.0:
                    continue
                dc = _colour_difference(L1, L2, r, c, p, half)
                do = _colour_difference(L1, L2, r, o, po, half)
                if dc > do + margin:
                    drop[c] = True
                    break
                if do > dc + margin:
                    drop[o] = True
            if not drop[c]:
                owner[b] = c
        count[r] = _set_dropped(row, drop, invalid)
    return count


@njit(cache=True)
def _set_dropped(row, drop, invalid):
    """``row[drop] = invalid``; returns how many."""
    n = 0
    for c in range(row.shape[0]):
        if drop[c]:
            row[c] = invalid
            n += 1
    return n


@njit(parallel=True, cache=True)
def _drop_fattened(disp, invalid, k, jump, tol):
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        row = disp[r]
        drop = np.zeros(width, np.bool_)
        last = -1  # the previous valid cell
        for c in range(width):
            if row[c] <= invalid:
                continue
            if last >= 0:
                step = row[c] - row[last]
                if abs(step) > jump and c - last - 1 <= abs(step) + tol:
                    if step > 0:  # the nearer surface starts at c
                        for t in range(c, min(c + k, width)):
                            drop[t] = row[t] > invalid
                    else:  # ... or ends at last
                        for t in range(max(last - k + 1, 0), last + 1):
                            drop[t] = row[t] > invalid
            last = c
        count[r] = _set_dropped(row, drop, invalid)
    return count


def drop_outside_windows(disp: np.ndarray, span2: np.ndarray, shift: int, invalid: float) -> int:
    """Set the disparities whose matching window (:data:`BLOCK` columns) in line image 2
    reaches beyond image 2's pixels to ``invalid``, in place; returns how many.

    ``span2`` (rows, 2): each row's first and last column of image 2's own pixels
    (:func:`.lines.line_images` with ``window=BLOCK``); ``disp`` holds columns of
    parallax, image 2's line image shifted by ``shift`` (a match at ``x`` lies at
    ``x - (d - shift)`` there). Such a window compares image 1 with the 0 beyond image
    2's edge: where a surface leaves image 2 (the forward and zoom scenes' borders:
    4.5-20 % of their matches had their true partner outside image 2) the cost there is
    no evidence of a match.

    The spans hold the cells whose rows within the window lie inside image 2 too: a
    window that reaches across image 2's edge compares the 0 beyond it (the converging
    pairs: rows that leave image 2 across its bottom edge), one along which the line runs
    (a rect pair's first and last rows) does not. Against each cell's own interpolation
    inside the image (its 4x4 pixels): real pairs 0.9425 / 0.8815 -> 0.9425 / 0.8825 at
    1 px (rect coverage 0.8835 -> 0.8868, conv 0.8784 -> 0.8774), generated 0.8428 /
    0.6336 -> 0.8438 / 0.6328.
    """
    return _drop_outside(disp, span2, float(shift), float(invalid), BLOCK // 2)


@njit(parallel=True, cache=True)
def _drop_outside(disp, span2, shift, invalid, half):
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        a, b = span2[r, 0] + half, span2[r, 1] - half
        for x in range(width):
            d = disp[r, x]
            if d > invalid:
                c2 = x - (d - shift)
                if c2 < a - 0.5 or c2 > b + 0.5:
                    disp[r, x] = invalid
                    count[r] += 1
    return count.sum()


def drop_unseen_far(disp: np.ndarray, span2: np.ndarray, shift: int, end: float, invalid: float) -> int:
    """Set the disparities below ``end`` (the searched range's far end before its
    :data:`END_COLUMNS`) to ``invalid``, in place, where the cell's matching window in
    line image 2 lies inside image 2 (``span2``, as :func:`drop_outside_windows`) only at
    parallax below ``end``; returns how many.

    At every depth the SIFT points span, such a cell's partner lies beyond image 2's edge:
    it is most likely not seen in image 2 at all (the forward and zoom scenes' rim, which
    image 2 does not see), and its estimate at the far end is where OpenCV puts its ties
    (the first disparity searched). Real surfaces beyond the SIFT points' far end (the
    plain walls of Midd1 and Midd2, 0.06-0.15 of their coverage in the far end columns)
    are seen by image 2 at nearer parallax too, and stay. Measured (true pose, p@1 / p@3 /
    cov@1): generated 0.8548 / 0.9206 / 0.6520 -> 0.8603 / 0.9264 / 0.6524 (forward and
    zoom +0.006..+0.022 of precision, no seed loses), real 0.9427 / 0.9664 / 0.8823 ->
    0.9430 / 0.9669 / 0.8825.
    """
    return _drop_unseen_far(disp, _first_seen(span2, shift, end, disp.shape[1]), float(end), float(invalid))


def _first_seen(span2: np.ndarray, shift: int, parallax: float, width: int) -> np.ndarray:
    """(rows,) int64: per row, the first column whose matching window image 2 holds at every
    parallax up to ``parallax`` (``drop_outside_windows``' bound: a cell at ``x`` sees image
    2 at parallax up to ``x + shift - (span2[r, 0] + BLOCK // 2) + 0.5``), within 0..width."""
    first = np.ceil(parallax - shift + span2[:, 0] + BLOCK // 2 - 0.5)
    return np.clip(first, 0, width).astype(np.int64)


@njit(parallel=True, cache=True)
def _drop_unseen_far(disp, first, end, invalid):
    count = np.zeros(disp.shape[0], np.int64)
    for r in prange(disp.shape[0]):
        for x in range(first[r]):
            if invalid < disp[r, x] < end:
                disp[r, x] = invalid
                count[r] += 1
    return count.sum()


def drop_unanchored_far(disp: np.ndarray, span2: np.ndarray, shift: int, end: float, near: float,
                        invalid: float) -> int:
    """Set the disparities below ``end`` (the far end columns, as :func:`drop_unseen_far`)
    of the cells that image 2 sees only at parallax below ``near`` (the range's near end
    before its :data:`END_COLUMNS`) to ``invalid``, in place, where their surface (the
    valid cells joined through neighbours, along a row or across rows, within
    :data:`SAME_SURFACE_COLUMNS`) reaches no cell that image 2 sees at every parallax of
    the range; returns how many.

    Such a cell's partner may lie beyond image 2's edge at a depth the scene has: the rim
    of image 1 that a forward or zoom pair's image 2 does not see. Its cost then holds no
    minimum, and its estimate falls where OpenCV puts its ties, at the far end
    (:func:`drop_unseen_far` drops those that image 2 sees at no nearer parallax at all;
    these see it at some). A real surface beyond the SIFT points that runs into the rim
    (the plain walls of Lampshade2 and Midd1, the cloth at Cloth2's left border, a
    generated wall whose parallax falls towards the left border) goes on where image 2
    sees every depth, and that part vouches for the rest. Measured (true pose, p@1 / p@3 /
    cov@1): generated 0.8676 / 0.9328 / 0.6577 -> 0.8818 / 0.9478 / 0.6580 (zoom seeds 3 and
    11 +0.073-0.076, forward seeds 2 and 6 +0.038-0.041 of precision, no seed down), real
    0.9492 / 0.9713 / 0.8823 -> 0.9499 / 0.9720 / 0.8825. The far end estimates alone as the
    surface (8-connected) cut a generated wall's strip at the left border off the rest of
    it, whose parallax lies just beyond the far end columns (seed 0: -0.004 of coverage,
    with its own pose -0.032); dropping every such estimate costs the real walls and cloth
    at the rim (Lampshade2 rect -0.024 of coverage).

    ``disp`` (rows, width) float32 parallax in columns, invalid at or below ``invalid``;
    ``span2`` (rows, 2) and ``shift`` as for :func:`drop_outside_windows`.
    """
    first = _first_seen(span2, shift, near, disp.shape[1])
    return int(_drop_unanchored(disp, first, float(end), float(invalid), SAME_SURFACE_COLUMNS))


@njit(cache=True)
def _root(parent, i):
    """The root of ``i`` in the union-find forest ``parent``, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True)
def _surface_forest(disp, invalid, tol):
    """Union-find forest (flat indices) of the valid cells of ``disp`` (above ``invalid``)
    joined through neighbours along a row or across rows within ``tol``: one tree per surface."""
    rows, width = disp.shape
    parent = np.arange(rows * width, dtype=np.int32)
    for r in range(rows):
        for x in range(width):
            d = disp[r, x]
            if d <= invalid:
                continue
            i = r * width + x
            for j, e in ((i + 1, x + 1 < width), (i + width, r + 1 < rows)):
                if e and disp.flat[j] > invalid and abs(disp.flat[j] - d) <= tol:
                    a, b = _root(parent, i), _root(parent, j)
                    if a != b:
                        parent[max(a, b)] = min(a, b)
    return parent


@njit(cache=True)
def _anchored_cells(parent, anchor):
    """(n,) bool: the cells whose tree in ``parent`` holds a cell of ``anchor``."""
    n = len(parent)
    root = np.empty(n, np.int32)
    anchored = np.zeros(n, np.bool_)
    for i in range(n):
        root[i] = _root(parent, i)
        if anchor[i]:
            anchored[root[i]] = True
    out = np.empty(n, np.bool_)
    for i in range(n):
        out[i] = anchored[root[i]]
    return out


@njit(cache=True)
def _drop_unanchored(disp, first, end, invalid, tol):
    rows, width = disp.shape
    # without a far end estimate that image 2 does not see at every parallax there is no
    # surface to find, nor a forest of the whole line image to build
    todo = False
    for r in range(rows):
        for x in range(first[r]):
            if invalid < disp[r, x] < end:
                todo = True
                break
        if todo:
            break
    if not todo:
        return 0
    anchor = np.zeros(rows * width, np.bool_)  # the estimates image 2 sees at every parallax
    for r in range(rows):
        for x in range(first[r], width):
            anchor[r * width + x] = disp[r, x] > invalid
    anchored = _anchored_cells(_surface_forest(disp, invalid, tol), anchor)
    count = 0
    for r in range(rows):
        for x in range(first[r]):
            if invalid < disp[r, x] < end and not anchored[r * width + x]:
                disp[r, x] = invalid
                count += 1
    return count


#: A run at a line's end is judged where it starts within this many cells of image 1's edge
#: (a window's width, BLOCK - 1: the flat check leaves the cells whose window reaches the
#: fill of one value beyond the edge, up to 2-3 cells in).
FRAME_RUN_REACH = BLOCK - 1
#: ...and puts that end within this many columns of image 2's edge: its first cell matched to
#: image 2's first cell, to within the interpolation's half column and OpenCV's half column.
FRAME_END_COLUMNS = 1.5


def drop_frame_end_runs(disp: np.ndarray, frames: np.ndarray, shift: int, invalid: float) -> int:
    """Set the runs of valid cells at a row's ends that match image 1's edge to image 2's
    and lie beside a nearer surface farther than a half-occlusion from them to ``invalid``,
    in place; returns how many cells.

    A run (consecutive valid cells) is judged where it starts within :data:`FRAME_RUN_REACH`
    cells of image 1's edge on the row and its first cell's partner lies as far from image
    2's edge, within :data:`FRAME_END_COLUMNS`: the two line images' ends matched to each
    other. Beyond a gap of cells without an estimate, the next run is nearer by more than
    :data:`MEDIAN_SAME_SURFACE` columns (another surface). A farther surface beside a nearer
    one leaves unmatched in image 1 the strip that the nearer hides in image 2, as wide as
    their parallax difference: where the gap is that wide (within :data:`MEDIAN_SAME_SURFACE`)
    or narrower, the run is a surface the two images' edges both see (a real pair's
    background at its border), and stays. Where the gap is wider, nothing in the scene
    explains it: image 1's end of the line, which image 2 does not see (the floor a forward
    camera moves over, below image 2), matched to image 2's end, and the run is dropped.

    ``disp`` (rows, width) float32 parallax in columns, image 2's line image shifted by
    ``shift`` (a cell ``x`` of parallax ``d`` matches ``x - (d - shift)``), invalid at or
    below ``invalid``; ``frames`` (2, rows, 2) each image's first and last column within its
    frame (:func:`.lines.line_images`, -1 where none).
    """
    return int(_drop_frame_end_runs(disp, frames, float(shift), float(invalid), FRAME_RUN_REACH, FRAME_END_COLUMNS,
                                    MEDIAN_SAME_SURFACE).sum())


@njit(parallel=True, cache=True)
def _drop_frame_end_runs(disp, frames, shift, invalid, reach, tol, same):
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        if frames[0, r, 0] < 0 or frames[1, r, 0] < 0:
            continue
        for side in range(2):  # the row's start (columns rising), then its end (falling)
            step = 1 if side == 0 else -1
            edge1, edge2 = frames[0, r, side], frames[1, r, side]
            f = 0 if side == 0 else width - 1
            while 0 <= f < width and disp[r, f] <= invalid:
                f += step
            if not 0 <= f < width:
                break
            partner = f - (disp[r, f] - shift)
            if step * (f - edge1) > reach or abs(step * (f - edge1) - step * (partner - edge2)) > tol:
                continue
            x = f  # the run's end (exclusive), then the gap's
            while 0 <= x < width and disp[r, x] > invalid:
                x += step
            y = x
            while 0 <= y < width and disp[r, y] <= invalid:
                y += step
            if not 0 <= y < width:
                continue
            jump = disp[r, y] - disp[r, x - step]
            if jump <= same or step * (y - x) <= jump + same:
                continue
            for k in range(f, x, step):
                disp[r, k] = invalid
            count[r] += step * (x - f)
    return count


def drop_occluded_plain(disp: np.ndarray, L1: np.ndarray, plain: np.ndarray, span2: np.ndarray, shift: int,
                        invalid: float) -> int:
    """Set the plain cells at the occlusion-side start of each nearer surface's run that
    continue the unmatched region before it to ``invalid``, in place; returns how many.

    Where a nearer surface meets a plain region that SGM left unmatched, its disparity
    runs on into the plain cells next to it: their cost is the same at every disparity and
    SGM's smoothness carries the nearer surface's in. On image 1's occlusion side (the
    smaller columns, as ``x2 = x1 - d``) those cells are the farther surface's strip hidden
    in image 2 (the walls beside Monopoly's board and Midd2's lampshade, pillow and hat;
    4-6 % of those pairs' matches lay on pixels hidden in image 2). Dropped are the valid
    cells at the start of a run that are plain (:func:`plain_windows`) and of the colour of
    the unmatched cell before the run, each channel within :data:`PLAIN_LEVELS` (the plain
    test's noise), and after them up to ``BLOCK // 2`` cells more of that colour, up to the
    intensity edge where the run's own surface begins; only where the run is the nearer
    surface (a valid cell before the gap lies more than ``2 * LR_MAX_DIFF`` columns
    farther) and the gap is not explained by image 2's edge: mapped with the run's
    parallax, its cells from the one before the hidden strip on (the strip: as many cells
    before the run as the two surfaces' parallax difference; the whole gap where that is
    narrower) lie inside image 2's windows. A run goes on
    across up to ``BLOCK // 2`` unmatched cells to a cell within ``2 * LR_MAX_DIFF``
    columns of its last: SGM's left-right check drops single cells at the nearer
    surface's own intensity edge, which ended the run before the edge and left the strip
    in place (the lateral test pair: 78 % of the hidden strip matched with the check, 36 %
    with the run bridged; the real pairs +0.0002 / -0.0002, the generated +0.0005 /
    -0.0005).

    Measured (p@1 / cov@1, true pose): the 60 real cases +0.0034 / -0.0014 (Midd2 conv
    0.841 -> 0.853, Plastic unrect 0.844 -> 0.851, Monopoly +0.017-0.023), the 20 generated
    seeds +0.0037 / -0.0016 (no seed's precision down). The ``BLOCK // 2`` cells next to the
    edge, whose windows reach it and are not plain, stayed matched with the nearer surface's
    parallax before (the 20 rect pairs: 1.3 % of the matches on pixels hidden in image 2, 62 %
    of them at the nearer surface's parallax); with them, the real pairs +0.0011 / 0.0000
    (precision at 3 px +0.0011: Midd2 +0.004, Baby2 +0.001), the generated seeds within 0.002
    each. The image-2 test on the strip's cells instead of the whole gap (a row whose
    last valid cell before the gap lies at image 1's border, where image 2 does not see,
    failed it with the whole gap, and Midd2's and Monopoly's strips stayed): the real
    pairs +0.0007 / -0.0001 (Midd2 +0.004-0.008, Monopoly +0.005-0.009 of precision, no
    case down by more than 0.001), the generated +0.0004 / -0.0001; on the gap's last 3
    cells alone: -0.0070 of coverage (Plastic conv -0.054, Wood2 up to -0.044).
    On both ends of each run: +0.0049 /
    -0.0047 on the real pairs (beyond a nearer surface's far end the background is seen in
    both images). Without the two tests (in grey, 16 cells at most): -0.0073 of coverage
    (plain surfaces at image 1's left border); comparing grey instead of colour: -0.0036
    (the cream lampshade on the grey wall).

    ``disp`` (rows, width) float32 parallax in columns, invalid at or below ``invalid``;
    ``L1`` (rows, width[, channels]) uint8 line image 1; ``plain`` (rows, width) bool
    (:func:`plain_windows`); ``span2`` (rows, 2) image 2's first and last column per row
    and ``shift`` as for :func:`drop_outside_windows`.
    """
    colour = L1 if L1.ndim == 3 else L1[:, :, None]
    return int(_drop_occluded_plain(disp, colour, plain, span2, float(shift), float(invalid), PLAIN_LEVELS,
                                    2.0 * LR_MAX_DIFF, BLOCK // 2).sum())


@njit(cache=True)
def _same_colour(L1, r, c, o, tol):
    """Every channel of ``L1[r, c]`` within ``tol`` of ``L1[r, o]``."""
    for ch in range(L1.shape[2]):
        if abs(float(L1[r, c, ch]) - float(L1[r, o, ch])) > tol:
            return False
    return True


@njit(cache=True)
def _on_surface(row, k, ref, invalid, jump):
    """Cell ``k`` lies in ``row``, is valid and within ``jump`` columns of cell ``ref``."""
    return 0 <= k < row.shape[0] and row[k] > invalid and abs(row[k] - row[ref]) <= jump


@njit(parallel=True, cache=True)
def _drop_occluded_plain(disp, L1, plain, span2, shift, invalid, tol, jump, half):
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        row = disp[r]
        drop = np.zeros(width, np.bool_)
        last = -1  # the last valid cell before the current gap
        c = 0
        while c < width:
            if row[c] <= invalid:
                c += 1
                continue
            a = c  # a run of valid cells a .. c - 1 after a gap from last + 1
            while c < width and row[c] > invalid:
                c += 1
                # across a gap of up to ``half`` cells to a cell on the same surface: one
                # run (SGM's left-right check drops single cells at the surface's own
                # intensity edges)
                g = c
                while g < width and g - c < half and row[g] <= invalid:
                    g += 1
                if c < g and _on_surface(row, g, c - 1, invalid, jump):
                    c = g
            nearer = last >= 0 and a > last + 1 and row[last] < row[a] - jump
            # the gap's cells that image 2 must see: from the cell before the hidden strip
            # (as many cells as the parallax difference, just before the run) on, or the
            # whole gap where it is narrower
            first = float(last + 1)
            if nearer:
                first = max(first, a - 1 - (row[a] - row[last]))
            inside = first - (row[a] - shift) >= span2[r, 0] + half
            if nearer and inside:
                k = a
                while k < c and plain[r, k] and _same_colour(L1, r, k, a - 1, tol):
                    k += 1
                # the last cells before the edge: their windows reach it (not plain), the
                # cells themselves are still of the strip's colour
                e = 0
                while k < c and e < half and _same_colour(L1, r, k, a - 1, tol):
                    k += 1
                    e += 1
                if a < k < c:  # an edge ends the plain strip inside the run
                    for x in range(a, k):
                        drop[x] = row[x] > invalid
            last = c - 1
        count[r] = _set_dropped(row, drop, invalid)
    return count


def drop_carried_plain(disp: np.ndarray, L1: np.ndarray, plain: np.ndarray, invalid: float) -> int:
    """Set the plain cells of a farther surface's colour that a nearer surface carries
    across a depth jump along the rows, up to the intensity edge where the nearer surface
    begins, to ``invalid``, in place; returns how many.

    On a plain region the cost is the same at every disparity, so SGM's smoothness sets
    the depth there, and beside a nearer surface it carries the nearer surface's parallax
    past the surfaces' boundary into the plain wall (the walls right of Midd1's pot and
    Midd2's lampshade, on image 2's visible side, where :func:`drop_occluded_plain` does not
    look: no unmatched strip lies between them). A true depth edge lies on an intensity
    edge; a jump on a plain region of one colour does not. At each jump of more than
    ``2 * LR_MAX_DIFF`` columns between consecutive valid cells of a row (neighbours, or
    across unmatched cells: SGM's checks leave gaps beside such bands), dropped are the
    nearer side's cells, walking away from the jump, that are plain (:func:`plain_windows`)
    and of the farther cell's colour (each channel within :data:`PLAIN_LEVELS`; the farther
    cell plain too), then up to ``BLOCK // 2`` more of that colour (their windows reach the
    edge), all on the nearer side's surface (within ``2 * LR_MAX_DIFF`` columns of its
    first cell); only where the walk ends at an intensity edge inside that surface: a valid
    cell on it, of another colour and not plain. A plain surface of another colour, a slow
    shading ramp (no window there is not plain) and a surface that ends without an edge
    keep their cells.

    Measured (p@1 / p@3 / cov@1, true pose): the 60 real cases 0.9437 / 0.9686 / 0.8810 ->
    0.9466 / 0.9712 / 0.8798 (Midd1 +0.010-0.012, Midd2 +0.008-0.011, Monopoly +0.008-0.009
    of precision; Plastic -0.010 to -0.016 of coverage); the 20 generated seeds 0.8672 /
    0.9325 / 0.6585 -> 0.8676 / 0.9329 / 0.6577, each within 0.002. Variants, all with the
    jumps across at most ``BLOCK // 2`` unmatched cells (real cases): that alone 0.9455 /
    0.9702 / 0.8806; without the edge's not-plain test 0.9457 / 0.9705 / 0.8777 (the white
    cloth of Bowling1, a slanted plain surface with steps of a few columns, lost 0.02 of
    coverage); without it and across the lines as well (the same walk over the columns of
    the line images) 0.9462 / 0.9709 / 0.8761. Of the cells that variant drops on Midd1 and
    Bowling1 (rect), 83-86 % were more than 3 px off. Where a wrong farther estimate lies
    inside a plain region, the jump is that estimate's, and the walk drops the region's
    right cells instead (the lateral test pair: 605 cells dropped, 22 % of them wrong).

    ``disp`` (rows, width) float32 parallax in columns, invalid at or below ``invalid``;
    ``L1`` (rows, width[, channels]) uint8 line image 1; ``plain`` (rows, width) bool.
    """
    colour = L1 if L1.ndim == 3 else L1[:, :, None]
    return int(_drop_carried_plain(disp, colour, plain, float(invalid), PLAIN_LEVELS, 2.0 * LR_MAX_DIFF,
                                   BLOCK // 2).sum())


@njit(parallel=True, cache=True)
def _drop_carried_plain(disp, L1, plain, invalid, tol, jump, half):
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        row = disp[r]
        drop = np.zeros(width, np.bool_)
        p = -1  # the last valid cell
        for q in range(width):
            if row[q] <= invalid:
                continue
            if p >= 0 and abs(row[q] - row[p]) > jump:
                # a jump between neighbours or across unmatched cells: walk from the
                # nearer side's first cell away from it
                if row[q] > row[p]:
                    far, start, step = p, q, 1
                else:
                    far, start, step = q, p, -1
                if plain[r, far]:
                    k = start
                    while (_on_surface(row, k, start, invalid, jump) and plain[r, k]
                           and _same_colour(L1, r, k, far, tol)):
                        k += step
                    e = 0
                    while _on_surface(row, k, start, invalid, jump) and e < half and _same_colour(L1, r, k, far, tol):
                        k += step
                        e += 1
                    # an intensity edge on the nearer surface ends the walk
                    if k != start and _on_surface(row, k, start, invalid, jump) and not plain[r, k]:
                        x = start
                        while x != k:
                            drop[x] = True
                            x += step
            p = q
        count[r] = _set_dropped(row, drop, invalid)
    return count


def flat_windows(L1: np.ndarray) -> np.ndarray:
    """(rows, width) bool: the cells of line image 1 whose matching window (:data:`BLOCK`
    square) holds a single value in every channel (:func:`drop_flat_windows`)."""
    # uint8 max - min over the window, then any channel's (OpenCV's or: numpy's max over
    # the channel axis took ten times as long)
    spread = cv2.morphologyEx(L1, cv2.MORPH_GRADIENT, np.ones((BLOCK, BLOCK), np.uint8))
    if spread.ndim == 3:
        spread = functools.reduce(cv2.bitwise_or, [spread[..., c] for c in range(spread.shape[2])])
    return spread == 0


def drop_flat_windows(disp: np.ndarray, L1: np.ndarray, invalid: float) -> int:
    """Set the disparities whose matching window (:data:`BLOCK` square) in line image 1
    reaches into an area of a single value in every channel to ``invalid``, in place;
    returns how many.

    Such an area carries no signal at all: a clipped black or white area (the dino's
    background), or the fill beyond a warped or undistorted image's edge. A window inside
    it costs the same at every disparity, so its estimate came from the aggregation paths
    alone, carried in from the surfaces around it; a window that reaches into it compares
    the area's edge, which is no edge of the scene where it is fill (the turned images'
    borders, matched to image 2's own fill edge: a line of wrong matches along them). The
    area is the union of the windows of one value (:func:`flat_windows`, an exact test,
    max = min, no threshold: an evenly lit real wall still varies by a grey level or so
    over 5x5 pixels), and a window reaches into it where its centre lies within
    ``BLOCK - 1`` cells of such a window's centre. Against dropping only the windows of one
    value (p@1 / cov@1, true pose): the real pairs 0.9385 / 0.8819 -> 0.9423 / 0.8813 (conv
    0.929 -> 0.939 of precision, rect unchanged), the generated scenes 0.8401 / 0.6354 ->
    0.8430 / 0.6338 (the forward scenes' oversampled epipole, where windows of one value
    lie); their centres alone, 0.9404 / 0.8820 on the real pairs.
    """
    reach = cv2.dilate(flat_windows(L1).view(np.uint8), np.ones((2 * BLOCK - 1, 2 * BLOCK - 1), np.uint8))
    drop = reach.view(bool) & (disp > invalid)
    disp[drop] = invalid
    return int(np.count_nonzero(drop))


def surface_median(disp: np.ndarray, invalid: float, passes: int = MEDIAN_PASSES, slanted: bool = True) -> None:
    """Replace each valid disparity (above ``invalid``) of ``disp`` (rows, columns) float32, in
    place, by the median of its 5x5 window where that lies within :data:`MEDIAN_SAME_SURFACE`
    columns of it, ``passes`` times.

    Invalid cells stay invalid and do not vote: they enter the window as +1e6 and -1e6 in a
    checkerboard, half above every disparity and half below, so the median is the valid
    cells' own (to within one rank where their count is odd). With ``slanted``, a cell whose
    window lies on one plane (:func:`local_planes`, within :data:`PLANE_RMS`) that slopes (by
    :data:`MEDIAN_MIN_SLOPE` or more) takes the median of the disparities less each one's
    window's plane, plus its own plane at the cell: on a slanted surface a window that holes cut on
    one side holds more cells of one end of the ramp, and a plain median is pulled that way
    (the floors that slope across the lines: seed 13's, 0.5-0.75 columns a line, lost 0.05
    of precision at 1 px to the median).
    """
    h, w = disp.shape
    valid = (disp > invalid).view(np.uint8)  # 0 / 1, as OpenCV's masks want
    checker = np.tile(np.array([[1e6, -1e6], [-1e6, 1e6]], np.float32), (h // 2 + 1, w // 2 + 1))[:h, :w]
    src = cv2.copyTo(disp, valid, checker.copy())
    plane = on_plane = None
    if slanted:
        plane, rms, slope = local_planes(disp, invalid)
        on_plane = cv2.bitwise_and(cv2.bitwise_and(valid, cv2.compare(rms, PLANE_RMS, cv2.CMP_LE)),
                                   cv2.compare(slope, MEDIAN_MIN_SLOPE, cv2.CMP_GE))  # 0 / 1
        off = checker.copy()  # its invalid cells keep the checkerboard; each pass sets the valid ones
    for _ in range(passes):
        med = cv2.medianBlur(src, 5)
        if plane is not None:
            cv2.copyTo(cv2.subtract(src, plane), valid, off)
            cv2.copyTo(cv2.add(cv2.medianBlur(off, 5), plane), on_plane, med)
        take = cv2.compare(cv2.absdiff(med, src), MEDIAN_SAME_SURFACE, cv2.CMP_LE)
        cv2.copyTo(med, cv2.bitwise_and(take, valid), src)  # compare gives 0 / 255
    cv2.copyTo(src, valid, disp)


def local_planes(disp: np.ndarray, invalid: float, half: int = PLAIN_FIT_HALF
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The least-squares plane through the valid disparities (above ``invalid``) of each valid
    cell's (2 ``half`` + 1)-cell square window of ``disp`` (rows, columns) float32: its value at
    the cell, the root mean square of the disparities about it and its steeper slope (the
    larger of its slopes along and across the lines, columns a cell), float32 each. Where the
    window holds fewer than :data:`PLANE_MIN_CELLS` valid cells or they lie on one line, and at
    invalid cells: the cell's own disparity, infinity and 0."""
    return _local_planes(disp, float(invalid), half, PLANE_ROWS_A_BLOCK)


@njit(parallel=True, cache=True)
def _local_planes(disp, invalid, half, block):
    rows, width = disp.shape
    plane = disp.copy()
    rms = np.full((rows, width), np.inf, np.float32)
    slope = np.zeros((rows, width), np.float32)
    for b in prange((rows + block - 1) // block):
        r0, r1 = b * block, min((b + 1) * block, rows)
        # each column's sums over the window's rows (count, row, row^2, d, d row, d^2), slid
        # down the block's rows: a row enters and a row leaves
        C = np.zeros((6, width))
        for rr in range(max(r0 - half, 0), min(r0 + half, rows - 1) + 1):
            _add_row(C, disp, rr, invalid, 1.0)
        P = np.zeros((10, width + 1))
        for r in range(r0, r1):
            if r > r0:
                if r + half < rows:
                    _add_row(C, disp, r + half, invalid, 1.0)
                if r - half - 1 >= 0:
                    _add_row(C, disp, r - half - 1, invalid, -1.0)
            # running sums along the row, rows relative to r (v = row - r)
            for c in range(width):
                n, s_r, s_rr, s_d, s_dr, s_dd = C[0, c], C[1, c], C[2, c], C[3, c], C[4, c], C[5, c]
                v1 = s_r - r * n
                v2 = s_rr - 2.0 * r * s_r + r * r * n
                vd = s_dr - r * s_d
                _prefix_step(P, c, n, v1, v2, s_d, vd, s_dd)
            for c in range(width):
                if disp[r, c] <= invalid:
                    continue
                lo, hi = max(c - half, 0), min(c + half + 1, width)
                n = P[0, hi] - P[0, lo]
                if n < PLANE_MIN_CELLS:
                    continue
                x = float(c)
                sx, sv, sd = P[1, hi] - P[1, lo], P[3, hi] - P[3, lo], P[6, hi] - P[6, lo]
                mu, mv, md = sx / n - x, sv / n, sd / n
                cuu = (P[2, hi] - P[2, lo]) / n - (sx / n) ** 2  # (shift-free)
                cvv = (P[5, hi] - P[5, lo]) / n - mv * mv
                cuv = (P[4, hi] - P[4, lo]) / n - (sx / n) * mv
                cud = (P[7, hi] - P[7, lo]) / n - (sx / n) * md
                cvd = (P[8, hi] - P[8, lo]) / n - mv * md
                a, b_ = _plane_slopes(cuu, cvv, cuv, cud, cvd)
                if np.isnan(a):
                    continue
                cdd = (P[9, hi] - P[9, lo]) / n - md * md
                plane[r, c] = md - a * mu - b_ * mv
                rms[r, c] = math.sqrt(max(cdd - a * cud - b_ * cvd, 0.0))
                slope[r, c] = max(abs(a), abs(b_))
    return plane, rms, slope


@njit(cache=True)
def _prefix_step(P, c, n, v1, v2, d1, vd, dd):
    """Extend the running sums ``P`` (10, columns + 1) along a row by column ``c``'s sums over
    the window's rows: count, rows (relative), rows squared, disparities, disparities times
    rows, disparities squared; with the column index as the running sums of the planes need."""
    x = float(c)
    P[0, c + 1] = P[0, c] + n
    P[1, c + 1] = P[1, c] + n * x
    P[2, c + 1] = P[2, c] + n * x * x
    P[3, c + 1] = P[3, c] + v1
    P[4, c + 1] = P[4, c] + v1 * x
    P[5, c + 1] = P[5, c] + v2
    P[6, c + 1] = P[6, c] + d1
    P[7, c + 1] = P[7, c] + d1 * x
    P[8, c + 1] = P[8, c] + vd
    P[9, c + 1] = P[9, c] + dd


@njit(cache=True)
def _add_row(C, disp, rr, invalid, sign):
    """Add (sign 1) or take out (-1) row ``rr`` of ``disp`` in the column sums ``C``."""
    row = float(rr)
    for c in range(disp.shape[1]):
        d = disp[rr, c]
        if d > invalid:
            C[0, c] += sign
            C[1, c] += sign * row
            C[2, c] += sign * row * row
            C[3, c] += sign * d
            C[4, c] += sign * d * row
            C[5, c] += sign * d * d


def plain_windows(L1: np.ndarray) -> np.ndarray:
    """(rows, width) bool: the cells of line image 1 whose :data:`BLOCK` square window has a
    grey-value standard deviation below :data:`PLAIN_LEVELS` (:func:`fit_plain_surfaces`)."""
    return quiet_windows(to_gray(L1), BLOCK, PLAIN_LEVELS)


def fit_plain_surfaces(disp: np.ndarray, plain: np.ndarray, invalid: float) -> int:
    """Replace each valid disparity of ``disp`` (rows, columns) float32 on a ``plain`` cell
    (:func:`plain_windows`), in place, by the value at the cell of the plane fitted (least
    squares over rows and columns) to the valid disparities of its (2 :data:`PLAIN_FIT_HALF`
    + 1)-cell square window that lie within :data:`MEDIAN_SAME_SURFACE` columns of its own,
    where they are at least :data:`PLAIN_FIT_SUPPORT` of the window; returns how many moved.
    Textured cells, invalid cells and cells on too little of their surface stay as they are.
    """
    side = 2 * PLAIN_FIT_HALF + 1
    need = max(3, int(math.ceil(PLAIN_FIT_SUPPORT * side * side)))
    # Where a window's valid disparities all lie within the tolerance of each other (its
    # spread, max - min, at most MEDIAN_SAME_SURFACE), every one of them is on the cell's
    # surface, and the window's sums come from running sums along the row (_fit_plain)
    valid = disp > invalid
    kernel = np.ones((side, side), np.uint8)
    high = cv2.dilate(np.where(valid, disp, np.float32(-1e9)), kernel)
    low = cv2.erode(np.where(valid, disp, np.float32(1e9)), kernel)
    whole = cv2.subtract(high, low) <= MEDIAN_SAME_SURFACE
    out = _fit_plain(disp, plain & valid, whole, float(invalid), PLAIN_FIT_HALF, MEDIAN_SAME_SURFACE, need)
    moved = out != disp
    disp[...] = out
    return int(np.count_nonzero(moved))


@njit(cache=True)
def _plane_at_cell(n, su, sv, sd, suu, svv, suv, sud, svd, d0):
    """The least-squares plane d = a u + b v + e through ``n`` cells given by their sums
    (u, v relative to the cell), at the cell (e); ``d0`` where the cells lie on one line."""
    mu, mv, md = su / n, sv / n, sd / n
    cuu, cvv, cuv = suu / n - mu * mu, svv / n - mv * mv, suv / n - mu * mv
    a, b = _plane_slopes(cuu, cvv, cuv, sud / n - mu * md, svd / n - mv * md)
    if np.isnan(a):
        return d0
    return md - a * mu - b * mv


@njit(cache=True)
def _plane_slopes(cuu, cvv, cuv, cud, cvd):
    """The slopes (a, b) of the least-squares plane d = a u + b v + e from the cells'
    (co)variances of u, v and d; (nan, nan) where the cells lie on one line (no plane)."""
    det = cuu * cvv - cuv * cuv
    if det <= 1e-6:
        return np.nan, np.nan
    return (cud * cvv - cvd * cuv) / det, (cvd * cuu - cud * cuv) / det


@njit(parallel=True, cache=True)
def _fit_plain(disp, todo, whole, invalid, half, tol, need):
    rows, width = disp.shape
    out = disp.copy()
    for r in prange(rows):
        if not todo[r].any():
            continue
        # column sums over the window's rows (v relative to row r), then prefix sums along
        # the row of them and of their products with the column index
        P = np.zeros((10, width + 1))
        for cc in range(width):
            n = v1 = v2 = d1 = vd = 0.0
            for rr in range(max(r - half, 0), min(r + half + 1, rows)):
                d = disp[rr, cc]
                if d > invalid:
                    v = float(rr - r)
                    n += 1.0
                    v1 += v
                    v2 += v * v
                    d1 += d
                    vd += v * d
            _prefix_step(P, cc, n, v1, v2, d1, vd, 0.0)
        for c in range(width):
            if not todo[r, c]:
                continue
            d0 = disp[r, c]
            if whole[r, c]:  # every valid cell of the window counts: sums from the prefixes
                lo, hi = max(c - half, 0), min(c + half + 1, width)
                n = P[0, hi] - P[0, lo]
                if n < need:
                    continue
                x = float(c)
                sx, sxx = P[1, hi] - P[1, lo], P[2, hi] - P[2, lo]
                sv, svx = P[3, hi] - P[3, lo], P[4, hi] - P[4, lo]
                sd, sdx = P[6, hi] - P[6, lo], P[7, hi] - P[7, lo]
                out[r, c] = _plane_at_cell(n, sx - x * n, sv, sd, sxx - 2.0 * x * sx + x * x * n,
                                           P[5, hi] - P[5, lo], svx - x * sv, sdx - x * sd, P[8, hi] - P[8, lo], d0)
                continue
            n = 0
            su = sv = sd = suu = svv = suv = sud = svd = 0.0
            for rr in range(max(r - half, 0), min(r + half + 1, rows)):
                v = float(rr - r)
                for cc in range(max(c - half, 0), min(c + half + 1, width)):
                    d = disp[rr, cc]
                    if d <= invalid or abs(d - d0) > tol:
                        continue
                    u = float(cc - c)
                    n += 1
                    su += u
                    sv += v
                    sd += d
                    suu += u * u
                    svv += v * v
                    suv += u * v
                    sud += u * d
                    svd += v * d
            if n >= need:
                out[r, c] = _plane_at_cell(float(n), su, sv, sd, suu, svv, suv, sud, svd, d0)
    return out


class GridScalars(NamedTuple):
    """What :func:`_read_back` needs of a :class:`.lines.LineGrid` and the disparity map."""

    phi0: float  #: ``phi`` of row 0, radians (the rows' angles rise from it)
    u_max: float
    u_step: float
    pad: float
    edge: float
    min_disparity: float  #: disparities below this are invalid
    interpolate: bool  #: over the cells on the nearest one's surface (else the nearest cell's)


@njit(parallel=True, cache=True)
def _read_back(disp, xs, reach, joined, g, basis, K1inv, P2, baseline, w1, y0, w2, h2, uv2, X, row):
    """For pixel ``i`` of image 1 (column ``i % w1``, row ``y0 + i // w1``): its ray's
    ``(phi, alpha)``, the disparity of the line images at its fractional row and
    column, interpolated over the neighbours on the nearest cell's surface, the
    position in image 2 of the ray at that parallax in the pixel's own half-plane, and
    the scene point where the two rays meet. Writes ``uv2`` (N, 2), ``X`` (N, 3) (camera
    1's frame) and ``row`` (N,) (-1: no match).

    Both rays lie in the half-plane: the point lies at ``baseline * sin(alpha2) /
    sin(alpha2 - alpha1)`` along the pixel's ray (the law of sines in the triangle of
    the two centres and the point), where the midpoint triangulation of the pair would
    put it, without its pass over the matches (0.19 s on the bench pair). Rays within
    1e-6 of parallel (as there) get no match.

    The cell nearest the pixel sets the surface (the pixel is unmatched when it is
    invalid: the matcher's checks rejected it). ``xs`` (rows,) the rows' ``phi`` less
    ``g.phi0`` (rising), ``reach`` and ``joined`` the grid's (:class:`.lines.LineGrid`);
    ``K1inv`` (3, 3) maps pixels to rays; ``P2`` (3, 3) = ``K2 R`` projects
    camera-1-axes rays into image 2.
    """
    n = row.shape[0]
    H, W = disp.shape
    two_pi = 2.0 * np.pi
    last = H - 1
    circle = joined[last]  # the rows go all round the epipole
    # Each ray's alpha is handled by its half-angle tangent tan(alpha / 2): it gives the
    # column (its log), the test against the epipole margin (alpha within ``edge`` of 0 or
    # pi) and image 2's ray (alpha's cosine and sine) without trigonometric calls: the
    # read-back took 0.21 s on the bench pair with them, 0.12 s without.
    t_lo = np.tan(0.5 * g.edge)
    t_hi = 1.0 / t_lo
    for i in prange(n):
        row[i] = -1
        r0, r1, r2 = pixel_ray(K1inv, i % w1 + 0.5, y0 + i // w1 + 0.5)
        rb = r0 * basis[0, 0] + r1 * basis[0, 1] + r2 * basis[0, 2]
        ra = r0 * basis[1, 0] + r1 * basis[1, 1] + r2 * basis[1, 2]
        re = r0 * basis[2, 0] + r1 * basis[2, 1] + r2 * basis[2, 2]
        rho = np.sqrt(ra * ra + re * re)
        if rho <= 0.0:
            continue
        nr = np.sqrt(rho * rho + rb * rb)
        th = rho / (nr + rb) if rb >= 0.0 else (nr - rb) / rho  # tan(alpha / 2), either form stable
        if th < t_lo or th > t_hi:
            continue
        phi = np.arctan2(re, ra)
        c = g.pad + (g.u_max - np.log(th)) / g.u_step
        x = phi - g.phi0
        x -= two_pi * np.floor(x / two_pi)
        if not circle and x > 0.5 * (xs[last] + two_pi):  # just below row 0, not past the last row
            x -= two_pi
        # the rows about the ray: q0 at or below it, q1 above (the first, 2 pi on, after the last)
        q0 = np.searchsorted(xs, x, side="right") - 1
        q1 = q0 + 1
        x0 = xs[q0] if q0 >= 0 else 0.0
        x1 = xs[q1] if q1 <= last else two_pi  # (xs[0] = 0)
        if q1 > last:
            q1 = 0 if circle else -1
        if q0 >= 0 and q1 >= 0 and joined[q0]:
            wk = (x - x0) / (x1 - x0)
        else:
            # a gap between rows, or beyond the first or last: the first and last rows
            # lie half a row inside image 1's outermost pixel centres, which are as near
            # the row beyond that does not exist; a row's cells reach its spacing
            # (``reach``) beyond it, and the nearer row that reaches the ray takes it
            if q0 >= 0 and x - x0 > reach[q0]:
                q0 = -1
            if q1 >= 0 and x1 - x > reach[q1]:
                q1 = -1
            wk = 0.0 if q0 >= 0 and (q1 < 0 or x - x0 <= x1 - x) else 1.0
        c0 = int(np.floor(c))
        wc = c - c0
        # the cell nearest the pixel sets the surface: where the matcher rejected it
        # (left-right check, uniqueness, speckle), the pixel stays unmatched
        rn = q0 if (wk < 0.5 and q0 >= 0) or q1 < 0 else q1
        cn = c0 + (1 if wc >= 0.5 else 0)
        if rn < 0 or cn < 0 or cn >= W or disp[rn, cn] < g.min_disparity:
            continue
        dn = disp[rn, cn]
        num = 0.0
        den = 0.0
        for j in range(4):
            rr = q0 if j < 2 else q1
            cc = c0 + (j & 1)
            w = (1.0 - wk if j < 2 else wk) * (1.0 - wc if (j & 1) == 0 else wc)
            if rr < 0 or cc < 0 or cc >= W:
                continue
            v = disp[rr, cc]
            if v >= g.min_disparity and abs(v - dn) <= SAME_SURFACE_COLUMNS:
                num += w * v
                den += w
        d = num / den if den > 0.0 and g.interpolate else dn
        # image 2's ray: tan(alpha2 / 2) from the column, its cosine and sine from that
        t2 = np.exp(g.u_max - (c - d - g.pad) * g.u_step)
        if t2 > 1.0:
            t2 = 1.0 / t2
            ca2 = (t2 * t2 - 1.0) / (t2 * t2 + 1.0)
        else:
            ca2 = (1.0 - t2 * t2) / (1.0 + t2 * t2)
        sa2 = 2.0 * t2 / (1.0 + t2 * t2)
        u, v, z = project_polar(P2, basis, ra / rho, re / rho, ca2, sa2)
        if z <= 1e-9:
            continue
        if u < 0.0 or u >= w2 or v < 0.0 or v >= h2:
            continue
        sd = sa2 * rb / nr - ca2 * rho / nr  # sin(alpha2 - alpha1)
        if sd <= 1e-6:
            continue
        s = baseline * sa2 / (sd * nr)  # the distance along the ray, over the ray's length
        uv2[i, 0] = u
        uv2[i, 1] = v
        X[i, 0] = r0 * s
        X[i, 1] = r1 * s
        X[i, 2] = r2 * s
        row[i] = rn


@njit(parallel=True, cache=True)
def _compact(uv2, X, row, w, y0, out1, out2, out_X, out_r, m0):
    """The matched pixels of a chunk (``row >= 0``) in pixel order, packed into ``out1``,
    ``out2`` (M, 2), ``out_X`` (M, 3) and ``out_r`` (M,) from index ``m0``: one parallel
    pass per image row (counting, then writing at each row's offset). Returns the index
    after the last."""
    nrows = row.shape[0] // w
    count = np.zeros(nrows + 1, np.int64)
    for r in prange(nrows):
        c = 0
        for j in range(r * w, (r + 1) * w):
            if row[j] >= 0:
                c += 1
        count[r + 1] = c
    start = np.cumsum(count) + m0
    for r in prange(nrows):
        m = start[r]
        for j in range(r * w, (r + 1) * w):
            if row[j] >= 0:
                out1[m, 0] = j - r * w + 0.5
                out1[m, 1] = y0 + r + 0.5
                out2[m, 0] = uv2[j, 0]
                out2[m, 1] = uv2[j, 1]
                out_X[m, 0] = X[j, 0]
                out_X[m, 1] = X[j, 1]
                out_X[m, 2] = X[j, 2]
                out_r[m] = row[j]
                m += 1
    return start[-1]


def pixel_matches(disp: np.ndarray, min_disparity: float, grid: LineGrid, tv: TwoView,
                  size1: tuple[int, int], size2: tuple[int, int], interpolate: bool = True):
    """One match per pixel of image 1 from a disparity map of the line images.

    ``disp`` (rows, width) float32 disparities in columns (``x2 = x1 - d``), invalid
    below ``min_disparity``. Each pixel centre's ray gives its fractional row and
    column; the disparity there is interpolated over the four cells around it that lie
    on the surface of the nearest one (within :data:`SAME_SURFACE_COLUMNS`), and the match is the
    ray at that parallax in the pixel's own half-plane, so it lies exactly on the
    pixel's epipolar line. Pixels nearer an epipole than ``grid.edge``, whose nearest cell
    is invalid, or whose match leaves image 2 get none.

    Returns ``(uv1, uv2, X, rows)``: (N, 2) COLMAP positions, (N, 3) their scene points
    (camera 1's frame, in front of both cameras) and (N,) rows of the line images, each
    the leading slice of an array of one row a pixel of image 1 (the room after it takes
    matches appended later without a copy, :func:`sefm_recon.arrays.append_rows`).
    """
    xs = np.ascontiguousarray(grid.phi - grid.phi[0], np.float64)
    reach = np.ascontiguousarray(grid.reach, np.float64)
    joined = np.ascontiguousarray(grid.joined, np.bool_)
    g = GridScalars(float(grid.phi[0]), float(grid.u_max), float(grid.u_step), float(grid.pad), float(grid.edge),
                    float(min_disparity), bool(interpolate))
    P2 = np.ascontiguousarray(tv.K2 @ tv.R)
    basis = np.ascontiguousarray(grid.basis, np.float64)
    K1inv = np.ascontiguousarray(np.linalg.inv(tv.K1))
    w, h = size1
    rows_per_chunk = max(1, _CHUNK_PIXELS // w)
    # numpy's outputs, one match a pixel at most, filled chunk by chunk and cut at the end
    # (arrays of numba's or a concatenation cost their size in fresh pages twice over)
    out1, out2, out_r = np.empty((w * h, 2)), np.empty((w * h, 2)), np.empty(w * h, np.int64)
    out_X = np.empty((w * h, 3))
    uv2 = np.empty((min(h, rows_per_chunk) * w, 2))
    X = np.empty((min(h, rows_per_chunk) * w, 3))
    row = np.empty(min(h, rows_per_chunk) * w, np.int64)
    baseline = float(np.linalg.norm(tv.t))
    m = 0
    for y0 in range(0, h, rows_per_chunk):
        n = w * (min(h, y0 + rows_per_chunk) - y0)
        _read_back(disp, xs, reach, joined, g, basis, K1inv, P2, baseline, w, y0, float(size2[0]), float(size2[1]),
                   uv2[:n], X[:n], row[:n])
        m = _compact(uv2[:n], X[:n], row[:n], w, y0, out1, out2, out_X, out_r, m)
    return out1[:m], out2[:m], out_X[:m], out_r[:m]


def _num_disparities(span: float) -> int:
    """OpenCV's ``numDisparities`` for a search over ``span`` columns: rounded up to a multiple of 16."""
    return int(math.ceil(span / 16.0)) * 16


def speckle_window(rows: int, columns: int, num_d: int, share: float | None = None) -> int:
    """The speckle filter's window (cells) for SGM over line images of ``rows`` x ``columns``
    cells searching ``num_d`` columns: ``share`` (default :data:`SPECKLE_SHARE`) of the cells
    it estimates (OpenCV leaves the first ``num_d`` columns without), at least
    :data:`SPECKLE_WINDOW`."""
    share = SPECKLE_SHARE if share is None else share
    return max(SPECKLE_WINDOW, int(share * rows * max(columns - num_d, 0)))


def _speckle_share(opt) -> float:
    """The speckle window's share of the view for ``opt`` (``cfg.sgm``): none where
    ``speckle_share`` is off (OpenCV's :data:`SPECKLE_WINDOW` alone)."""
    return SPECKLE_SHARE if opt.speckle_share else 0.0


def _sgbm(L1: np.ndarray, L2: np.ndarray, min_d: int, num_d: int, uniqueness: int, *, full_paths: bool = True,
          speckle: bool = True, jump: int = JUMP_PENALTY, speckle_share: float | None = None
          ) -> tuple[np.ndarray, bool]:
    """OpenCV's StereoSGBM (the settings above) over line images whose image 2 is shifted by
    ``min_d``, searching ``num_d`` columns: the disparity map (float32 columns, invalid below
    ``min_d``) and whether the four full paths ran (where the cost volume fits :data:`MAX_FULL_VOLUME`)."""
    cn = L1.shape[2] if L1.ndim == 3 else 1
    full = full_paths and _volume_fits(L1, num_d)
    window = speckle_window(*L1.shape[:2], num_d, speckle_share) if speckle else 0
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num_d, blockSize=BLOCK,
                                 P1=STEP_PENALTY * cn * BLOCK**2, P2=jump * cn * BLOCK**2,
                                 disp12MaxDiff=LR_MAX_DIFF, uniquenessRatio=uniqueness,
                                 speckleWindowSize=window,
                                 speckleRange=SPECKLE_RANGE,
                                 mode=cv2.STEREO_SGBM_MODE_HH4 if full else cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    # fixed point, 4 fractional bits; invalid: -1 (below min_d once shifted); one float copy
    disp = sgbm.compute(L1, L2).astype(np.float32)
    disp *= 1.0 / 16.0
    disp += min_d
    return disp, full


def drop_left_right(disp: np.ndarray, halves: tuple[np.ndarray, np.ndarray] | None, shift: int, num_d: int,
                    jump: int, full_paths: bool, invalid: float) -> int:
    """The left-right check: set the disparities that a second SGM, from image 2 to image 1,
    contradicts to ``invalid``, in place; returns how many.

    The second SGM runs over the mirrored line images reduced :data:`LR_REDUCTION` times
    (the same penalties, ``jump`` and aggregation, ``full_paths``; no uniqueness test, no
    speckle filter: it is asked where each cell of image 2 matches best, not whether it is
    sure). An estimate of ``disp`` whose partner lies between two reduced cells of image 2
    is dropped where both of them hold a parallax more than :data:`LR_MAX_DIFF` reduced
    columns from its own: a cell matched onto a surface whose own match lies elsewhere (the
    aperture of stripes along the lines, a partner that image 2 does not see, a plain region
    matched by chance). Where neither holds one (beyond the second search) it stays.

    ``disp`` (rows, width) float32 parallax in columns, invalid at or below ``invalid``;
    ``halves`` the line images SGM matched, reduced (:func:`halve_line_images`; None: too
    small, nothing judged), image 2's shifted by ``shift`` columns (a cell ``x`` of parallax
    ``d`` matches ``x - (d - shift)`` in line image 2), searched over ``num_d`` columns.
    """
    f = LR_REDUCTION
    if halves is None:
        return 0
    r1, r2 = (np.ascontiguousarray(r[:, ::-1]) for r in halves)
    nd = _num_disparities(num_d / f)
    back, _ = _sgbm(r2, r1, 0, nd, 0, full_paths=full_paths, speckle=False, jump=jump)
    back = np.ascontiguousarray(back[:, ::-1])  # parallax of image 2's reduced cells, -1: none
    return int(_drop_left_right(disp, back, float(shift), float(invalid), float(f), float(LR_MAX_DIFF)).sum())


@njit(parallel=True, cache=True)
def _drop_left_right(disp, back, shift, invalid, f, tol):
    rows, width = disp.shape
    rows_r, width_r = back.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        rr = min(int(r // f), rows_r - 1)
        for x in range(width):
            d = disp[r, x]
            if d <= invalid:
                continue
            d_r = (d - shift) / f
            # the partner's column in the reduced image 2 (pixel centres: (c + 0.5) / f - 0.5)
            c = (x - (d - shift) + 0.5) / f - 0.5
            c0 = int(np.floor(c))
            if c0 < 0 or c0 + 1 >= width_r:
                continue
            a, b = back[rr, c0], back[rr, c0 + 1]
            if (a < 0 and b < 0) or (a >= 0 and abs(a - d_r) <= tol) or (b >= 0 and abs(b - d_r) <= tol):
                continue
            disp[r, x] = invalid
            count[r] += 1
    return count


def halve_line_images(L1: np.ndarray, L2: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Copies of the line images ``L1``, ``L2`` reduced :data:`LR_REDUCTION` times on both axes
    (area average, cut to a multiple of it), for :func:`fill_from_half_size` and
    :func:`drop_left_right`; None where they would hold fewer lines or columns than a
    window (:data:`BLOCK`): nothing to match there."""
    f = LR_REDUCTION
    size = (L1.shape[1] // f, L1.shape[0] // f)
    if min(size) < BLOCK:
        return None
    return tuple(cv2.resize(L[: f * size[1], : f * size[0]], size, interpolation=cv2.INTER_AREA) for L in (L1, L2))


def half_size_sgm(halves: tuple[np.ndarray, np.ndarray] | None, num_d: int, jump: int, full_paths: bool,
                  uniqueness: int, speckle: bool, speckle_share: float | None = None) -> np.ndarray | None:
    """SGM over the line images reduced :data:`LR_REDUCTION` times on both axes (``halves``,
    :func:`halve_line_images`; None: too small, None back), with the full-size run's
    penalties (``jump``), aggregation, ``uniqueness`` test and ``speckle`` filter (its window
    ``speckle_share`` of the cells, :func:`speckle_window`), searching
    ``num_d`` full-size columns: (rows, width) of the reduced cells, float32 reduced columns
    of parallax from image 2's shifted line image, invalid below 0. A texture of low contrast
    (clouds, a mottled wall) carries little signal in a full-size window against the sensor
    noise; halved, its windows see twice the texture and half the noise."""
    if halves is None:
        return None
    r1, r2 = halves
    half, _ = _sgbm(r1, r2, 0, _num_disparities(num_d / LR_REDUCTION), uniqueness, full_paths=full_paths,
                    speckle=speckle, jump=jump, speckle_share=speckle_share)
    return half


def drop_off_half_size(disp: np.ndarray, half: np.ndarray | None, shift: int, invalid: float) -> int:
    """Coarse to fine as a check: set the full-size estimates more than
    :data:`HALF_CHECK_COLUMNS` columns from the half-size SGM's to ``invalid``, in place,
    where that one is sure (every reduced cell of the :data:`HALF_CHECK_SQUARE` square about
    the cell valid and within :data:`HALF_CHECK_SPREAD` reduced columns of each other, the
    four about the cell within one, as the fill asks; the estimate compared is their
    bilinear one); returns how many.

    Where the two levels disagree on one surface, the full-size window saw less of the
    texture: stripes along the lines matched a period off, a cloud wall's noise. The fill
    (:func:`fill_from_half_size`, run next) gives such a cell the reduced estimate where that
    passes its own test. ``disp`` (rows, width) float32 parallax in columns, image 2's line
    image shifted by ``shift``; ``half`` :func:`half_size_sgm`'s (None: nothing judged).
    """
    if half is None:
        return 0
    square = np.ones((HALF_CHECK_SQUARE, HALF_CHECK_SQUARE), np.uint8)
    top, low = cv2.dilate(half, square), cv2.erode(half, square)  # (cells beyond the border do not count)
    sure = np.where((low >= 0) & (top - low <= HALF_CHECK_SPREAD), half, np.float32(-1.0))
    return int(_drop_off_reduced(disp, sure, float(shift), float(invalid), float(LR_REDUCTION),
                                 HALF_CHECK_COLUMNS).sum())


@njit(parallel=True, cache=True)
def _drop_off_reduced(disp, half, shift, invalid, f, tol):
    """Set each estimate of ``disp`` (above ``invalid``) more than ``tol`` columns from the
    bilinear estimate of the four cells of ``half`` (``disp`` reduced ``f`` times, image 2
    unshifted, invalid below 0) about its centre, times ``f`` plus ``shift``, to ``invalid``,
    where all four are valid and within a reduced column of each other (as the fill asks);
    returns the count per row."""
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        for x in range(width):
            if disp[r, x] <= invalid:
                continue
            est = _reduced_estimate(half, r, x, f)
            if est >= 0 and abs(disp[r, x] - (est * f + shift)) > tol:
                disp[r, x] = invalid
                count[r] += 1
    return count


@njit(cache=True, inline="always")  # (called per cell: 0.05 s on arrays of the bench pair's size; inlined 0.018 s)
def _reduced_estimate(half, r, x, f):
    """The bilinear estimate at cell (``r``, ``x``) of the four cells of ``half`` (reduced ``f``
    times, invalid below 0) about its centre, where all four are valid and lie within one
    reduced column of each other (one surface); -1 elsewhere (beyond the first or last
    reduced column)."""
    rows_r, width_r = half.shape
    yr = (r + 0.5) / f - 0.5  # the reduced position of the cell's centre
    r0 = int(np.floor(yr))
    wy = yr - r0
    xr = (x + 0.5) / f - 0.5
    c0 = int(np.floor(xr))
    wx = xr - c0
    if c0 < 0 or c0 + 1 >= width_r:
        return -1.0
    lo = np.inf
    hi = -np.inf
    num = 0.0
    for j in range(4):
        rr = min(max(r0 + (j >> 1), 0), rows_r - 1)  # the first and last lines: the nearest reduced one
        v = half[rr, c0 + (j & 1)]
        lo = min(lo, v)
        hi = max(hi, v)
        num += (wy if j >> 1 else 1.0 - wy) * (wx if j & 1 else 1.0 - wx) * v
    if lo < 0 or hi - lo > 1.0:
        return -1.0
    return num


def fill_from_half_size(disp: np.ndarray, halves: tuple[np.ndarray, np.ndarray] | None, half: np.ndarray | None,
                        shift: int, invalid: float) -> int:
    """Coarse to fine: give the cells SGM left without an estimate (``disp`` at or below
    ``invalid``) the estimate of :func:`half_size_sgm` (``half``, over ``halves``; None:
    nothing filled; overwritten), in place; returns how many.

    A reduced cell counts where its window's derivative correlates with its partner's by
    :data:`FILL_MIN_ZNCC` (a shaded plain surface does not), and a full-size cell takes the
    bilinear estimate of the four reduced cells about it where all four count and lie within
    a reduced column of each other (one surface). The checks after SGM (the left-right
    check first) judge these estimates as SGM's own.

    ``disp`` (rows, width) float32 parallax in columns, image 2's line image shifted by
    ``shift`` columns.
    """
    f = LR_REDUCTION
    if halves is None or half is None:
        return 0
    r1, r2 = halves
    # a reduced cell k is read only for the cells of rows (and columns) 2k - 1 .. 2k + 2
    # without an estimate: the others need no test (most of a textured pair's)
    unset = cv2.dilate((disp <= invalid).view(np.uint8), np.ones((2 * f, 2 * f), np.uint8), anchor=(f - 1, f - 1))
    half[unset[::f, ::f][: half.shape[0], : half.shape[1]] == 0] = -1.0
    d1, d2 = (cv2.Sobel(to_gray(r), cv2.CV_32F, 1, 0, ksize=3) for r in (r1, r2))
    _drop_uncorrelated(half, d1, d2, FILL_WINDOW // 2, FILL_MIN_ZNCC)
    return int(_fill_from_reduced(disp, half, float(shift), float(invalid), float(f)).sum())


@njit(parallel=True, cache=True)
def _drop_uncorrelated(disp, g1, g2, half, min_zncc):
    """Set ``disp``'s estimates (invalid: below 0; image 2 unshifted) to -1 where the ZNCC
    (:func:`.zncc.zncc`) of ``g1``'s (2 ``half`` + 1) square window about the cell with
    ``g2``'s about its partner (linear between columns) is below ``min_zncc``, or where the
    window leaves either line image along the line."""
    rows = disp.shape[0]
    for r in prange(rows):
        # the window's lines as channels: columns along the first axis
        a = g1[max(r - half, 0): r + half + 1].T
        b = g2[max(r - half, 0): r + half + 1].T
        for x in range(disp.shape[1]):
            d = disp[r, x]
            if d >= 0 and zncc(a, x, b, x - d, half) < min_zncc:
                disp[r, x] = -1.0


@njit(parallel=True, cache=True)
def _fill_from_reduced(disp, half, shift, invalid, f):
    """Give each cell of ``disp`` at or below ``invalid`` the bilinear estimate of the four
    cells of ``half`` (``disp`` reduced ``f`` times, image 2 unshifted, invalid below 0)
    about its centre, times ``f`` plus ``shift``, where all four are valid and lie within
    one reduced column of each other; returns the count per row."""
    rows, width = disp.shape
    count = np.zeros(rows, np.int64)
    for r in prange(rows):
        for x in range(width):
            if disp[r, x] > invalid:
                continue
            est = _reduced_estimate(half, r, x, f)
            if est >= 0:
                disp[r, x] = est * f + shift
                count[r] += 1
    return count


def jump_ladder(count: Callable[[int], int]) -> int:
    """The jump penalty where ``count`` (penalty -> cells kept) stops growing: from
    :data:`JUMP_PENALTY` towards the better of half and twice it, by factors of two while
    each step keeps more than :data:`JUMP_MARGIN` more, within :data:`JUMP_MIN`..:data:`JUMP_MAX`."""
    jump = JUMP_PENALTY
    step = max((2.0, 0.5), key=lambda f: count(int(jump * f)))
    while JUMP_MIN <= jump * step <= JUMP_MAX and count(int(jump * step)) > (1 + JUMP_MARGIN) * count(jump):
        jump = int(jump * step)
    return jump


def _volume_fits(L1: np.ndarray, num_d: int) -> bool:
    """Whether the cost volume of line images shaped as ``L1`` over ``num_d`` columns fits
    :data:`MAX_FULL_VOLUME` (OpenCV's four full paths; else its 3 directions)."""
    return L1.shape[0] * L1.shape[1] * num_d <= MAX_FULL_VOLUME


def _cells_kept(L1: np.ndarray, L2: np.ndarray, num_d: int, opt,
                reduction: int) -> tuple[Callable[[int], int], dict[int, int]]:
    """``(count, kept)``: ``count`` maps a jump penalty to the cells SGM keeps through ``opt``'s
    checks on copies of the line images reduced ``reduction`` times on both axes (each
    penalty run once); ``kept`` holds the counts run so far."""
    size = (L1.shape[1] // reduction, L1.shape[0] // reduction)
    s1, s2 = (cv2.resize(L, size, interpolation=cv2.INTER_AREA) for L in (L1, L2))
    nd = _num_disparities(num_d / reduction)
    # the aggregation the full-size run will use (four full paths only where its volume fits)
    full = opt.full_paths and _volume_fits(L1, num_d)
    flat = flat_windows(s1) if opt.flat_check else None  # the same for every penalty
    kept: dict[int, int] = {}

    def count(jump: int) -> int:
        if jump not in kept:
            disp, _ = _sgbm(s1, s2, 0, nd, opt.uniqueness, full_paths=full, speckle=opt.speckle, jump=jump,
                            speckle_share=_speckle_share(opt))
            if flat is not None:
                disp[flat] = -1.0
            if opt.end_check:
                drop_range_ends(disp, 0, nd - 1, -1.0)
            kept[jump] = int(np.count_nonzero(disp >= 0))
        return kept[jump]

    return count, kept


def choose_jump_penalty(L1: np.ndarray, L2: np.ndarray, num_d: int, opt) -> int:
    """SGM's jump penalty P2 (a multiple of C B^2) for line images ``L1``, ``L2`` (image 2's
    shifted so that the search is ``0..num_d``), with ``opt``'s (``cfg.sgm``) switches.

    SGM runs on copies reduced :data:`CHOICE_REDUCTION` times, and :func:`jump_ladder`
    follows the cells it keeps through its checks. First, coarse to fine, on copies
    reduced twice as much: where half and twice :data:`JUMP_PENALTY` keep the same cells as
    it within :data:`JUMP_MARGIN`, the penalty does not matter to the pair and it is kept
    without the larger copies.
    """
    def seen(kept: dict[int, int]) -> str:
        return ", ".join(f"{n} with {j}" for j, n in sorted(kept.items()))

    coarse, coarse_kept = _cells_kept(L1, L2, num_d, opt, 2 * CHOICE_REDUCTION)
    base = max(coarse(JUMP_PENALTY), 1)
    if all(abs(coarse(j) / base - 1) < JUMP_MARGIN for j in (JUMP_PENALTY // 2, 2 * JUMP_PENALTY)):
        logger.info("jump penalty %d: cells kept at 1/%d size %s", JUMP_PENALTY, 2 * CHOICE_REDUCTION,
                    seen(coarse_kept))
        return JUMP_PENALTY
    logger.debug("cells kept at 1/%d size %s", 2 * CHOICE_REDUCTION, seen(coarse_kept))
    count, kept = _cells_kept(L1, L2, num_d, opt, CHOICE_REDUCTION)
    jump = jump_ladder(count)
    logger.info("jump penalty %d: cells kept at 1/%d size %s", jump, CHOICE_REDUCTION, seen(kept))
    return jump


@dataclass
class CoarseParallax:
    """What the coarse pass (:func:`coarse_parallax`) found."""

    parallax: np.ndarray  #: (rows, columns) float32 of ``grid``: full-size columns of parallax, NaN where none
    textured: np.ndarray  #: (rows, columns) bool: the cell's window is not plain (:func:`plain_windows`)
    step: float  #: full-size columns per coarse column
    grid: LineGrid | None = None  #: the coarse line images' grid (None: no place given, :func:`extend_near` alone)

    def at(self, grid: LineGrid, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(n,) the parallax at the coarse cell nearest each cell (``rows``, ``cols``) of
        the full-size ``grid``; NaN where none (beyond the coarse line images)."""
        g = self.grid
        r = np.round(np.interp(grid.phi[rows], g.phi, np.arange(len(g.phi)))).astype(np.intp)
        c = np.round(g.column(grid.alpha(cols))).astype(np.intp)
        inside = (c >= 0) & (c < self.parallax.shape[1])
        out = np.full(len(rows), np.nan, np.float32)
        out[inside] = self.parallax[r[inside], c[inside]]
        return out


def coarse_parallax(img1: np.ndarray, img2: np.ndarray, tv: TwoView, grid: LineGrid, cfg: Config,
                    lo: float, hi: float) -> CoarseParallax | None:
    """The parallax (columns of ``grid``) SGM finds on reduced copies of the images when it
    searches parallax columns ``lo..hi``; None where it finds none.

    The images are reduced (area average) by the smallest power of two from 2 that brings
    their line images to at most :data:`COARSE_COLUMNS` columns; estimates at the ends of the
    coarse search are dropped (:func:`drop_range_ends`).
    """
    factor = 2
    while grid.columns / factor > COARSE_COLUMNS:
        factor *= 2
    small, Ks = [], []
    for img, K in ((img1, tv.K1), (img2, tv.K2)):
        h, w = img.shape[:2]
        im = cv2.resize(img, (-(-w // factor), -(-h // factor)), interpolation=cv2.INTER_AREA)
        small.append(im)
        Ks.append(np.diag([im.shape[1] / w, im.shape[0] / h, 1.0]) @ K)  # COLMAP positions scale as the image
    size1, size2 = ((im.shape[1], im.shape[0]) for im in small)
    tvc = TwoView(Ks[0], Ks[1], tv.R, tv.t)
    gc = line_grid(tvc, size1, size2, cfg.lines.max_lines)
    if len(gc.phi) == 0:
        return None
    to_fine = gc.u_step / grid.u_step  # full-size columns per coarse column
    min_d = int(math.floor(lo / to_fine)) - 1
    num_d = _num_disparities(hi / to_fine - min_d + 2)
    gc.pad = num_d + 1
    L1, L2 = line_images(small[0], small[1], tvc, gc, gc.pad + gc.columns + 1, shift2=min_d, bicubic=False)
    disp, _ = _sgbm(L1, L2, min_d, num_d, cfg.sgm.uniqueness, speckle_share=_speckle_share(cfg.sgm))
    drop_range_ends(disp, min_d, min_d + num_d - 1, min_d - 1.0)
    found = disp >= min_d
    if not found.any():
        return None
    logger.info("coarse pass (1/%d size) over parallax %.0f..%.0f columns", factor, lo, hi)
    return CoarseParallax(np.where(found, disp * np.float32(to_fine), np.float32(np.nan)), ~plain_windows(L1), to_fine,
                          gc)


def coarse_range(img1: np.ndarray, img2: np.ndarray, tv: TwoView, grid: LineGrid, cfg: Config,
                 lo: float, hi: float) -> tuple[float, float] | None:
    """(lo, hi) columns of ``grid`` that hold the surfaces the coarse pass
    (:func:`coarse_parallax`) finds when it searches parallax columns ``lo..hi``: its
    estimates between :data:`COARSE_PERCENTILES`; None where it finds none."""
    found = coarse_parallax(img1, img2, tv, grid, cfg, lo, hi)
    if found is None:
        return None
    c_lo, c_hi = np.percentile(found.parallax[np.isfinite(found.parallax)], COARSE_PERCENTILES)
    logger.info("coarse pass: parallax %.0f..%.0f columns found in %.0f..%.0f", c_lo, c_hi, lo, hi)
    return float(c_lo), float(c_hi)


def _on_textured_surface(found: CoarseParallax) -> np.ndarray:
    """(rows, columns) bool: the coarse estimates on a surface (joined through neighbours
    along a row or across rows within one coarse column, :data:`SAME_SURFACE_COLUMNS`)
    that holds a textured one (:attr:`CoarseParallax.textured`)."""
    finite = np.isfinite(found.parallax)
    p = np.where(finite, found.parallax, -np.inf).astype(np.float32)
    parent = _surface_forest(p, -np.inf, SAME_SURFACE_COLUMNS * found.step)
    return _anchored_cells(parent, (found.textured & finite).ravel()).reshape(p.shape) & finite


def extend_near(hi: float, found: CoarseParallax) -> float:
    """``hi`` (columns of parallax) raised along the coarse pass's estimates beyond it on
    textured surfaces (:func:`_on_textured_surface`), as long as each lies within
    :data:`MARGIN_COLUMNS` and one coarse column of the last: a surface that comes nearer
    than the SIFT points (a floor towards the camera) fills the parallax beyond them
    without a gap; a wrong match lies apart.

    A surface's plain cells count where one of its cells is textured: a weakly textured
    near surface has textured cells only here and there along its parallax. Bowling1's
    ball (conv) had them at 51, 59-61 and 63-68 columns with the true pose, and with the
    pose the tool estimates none between 52 and 62, so the search stopped at 52 and the
    near end check then dropped the ball's nearer cells (1,542; coverage 0.843 against
    the true pose's 0.865). Its plain cells, on the surface of the textured ones, fill
    51-68 either way (own pose 0.856; the true pose's runs 0.865 in conv, +0.005 in rect
    and unrect); the generated scenes did not change (0.9219 / 0.9800 / 0.6908 at 1 px,
    3 px and coverage).

    Only the near side: SIFT misses near surfaces (they change scale and shape most
    between the views: the zoom scenes' floors, seed 9's checkerboard), while on the far
    side the coarse estimates beyond the SIFT points were plain walls carried towards
    parallax 0, none real (Midd1, Midd2, Monopoly: 8-22 % of their estimates).
    """
    p = np.unique(found.parallax[_on_textured_surface(found) & (found.parallax > hi)])  # (NaN > hi is False)
    if len(p) == 0:
        return hi
    gaps = np.diff(p, prepend=hi) > MARGIN_COLUMNS + found.step
    stop = int(np.argmax(gaps)) if gaps.any() else len(p)
    return float(p[stop - 1]) if stop else hi


def drop_unsupported_near(disp: np.ndarray, grid: LineGrid, found: CoarseParallax, near: float, end: float,
                          invalid: float) -> int:
    """Set the disparities of ``disp`` (rows, columns of ``grid``) beyond ``end`` (the
    searched range's near end before its :data:`END_COLUMNS`) to ``invalid``, in place,
    where the coarse pass (``found``) at the same place found no surface beyond ``near``
    (the SIFT points' near end, or the surface :func:`extend_near` followed); returns
    how many.

    SGM's wrong minima on plain and unseen regions fall at the ends of the search (the
    generated scenes: 2-10 % of the matches at the near end, up to 100 px from their
    true parallax); a surface really there, nearer than the SIFT points, is found by
    the coarse pass too (Bowling1's near ball: 15 % of its matches, 96 % within 1 px,
    kept). Only the near end: at the far end the coarse pass's own ties fall (OpenCV
    takes the first disparity searched, the farthest), so it holds no evidence there
    (checked the same way at the far end, the plain walls of Midd1 and Midd2 that lie
    beyond their SIFT points lost 0.06-0.11 of coverage).
    """
    rows, cols = np.nonzero(disp > end)
    if len(rows) == 0:
        return 0
    there = found.at(grid, rows, cols)
    drop = ~(there > near)  # NaN: no surface found there
    disp[rows[drop], cols[drop]] = invalid
    return int(np.count_nonzero(drop))


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
    opt = cfg.sgm
    lo, hi = search_range(tv, grid, size1, opt.range_margin, opt.sift_range)
    found = None  # the coarse pass towards the camera, where it runs (and `near`, its near end)
    if len(tv.kp1) >= 8 and opt.sift_range and (opt.near_range or opt.near_check):
        # a coarse pass for the surfaces nearer than the SIFT points
        s_lo, near = sift_parallax_columns(tv, grid)
        nearest = parallax_columns(tv, grid, size1, (depth_range(tv, NEAR_DEPTH)[0],))[1]
        found = coarse_parallax(img1, img2, tv, grid, cfg, lo, max(hi, nearest + END_COLUMNS + 1))
        if found is not None and opt.near_range:
            s_hi, near = near, extend_near(near, found)
            if near > hi - END_COLUMNS - 1:  # beyond the margin the SIFT range is searched with
                logger.info("search extended towards the camera: SIFT parallax %.0f..%.0f columns, a surface found "
                            "up to %.0f", s_lo, s_hi, near)
                hi = widen_range(s_lo, near, opt.range_margin)[1]
    if len(tv.kp1) < 8 and opt.coarse_range:  # no SIFT range: every depth, unless a coarse pass narrows it
        spans = coarse_range(img1, img2, tv, grid, cfg, lo, hi)
        if spans is not None:
            # widened as a SIFT range is (the margin's 8 columns exceed a coarse column up to 1/8 size)
            c_lo, c_hi = widen_range(*spans, opt.range_margin)
            lo, hi = max(lo, c_lo), min(hi, c_hi)
    min_d = int(math.floor(lo))
    num_d = _num_disparities(hi - lo + 1)
    # Image 2's line image is shifted by min_d, so that OpenCV searches 0..num_d; the pad
    # left of image 1's columns holds the search window of its first columns.
    grid.pad = num_d + 1
    width = grid.pad + grid.columns + 1
    L1, L2, span2, frames = line_images(img1, img2, tv, grid, width, shift2=min_d, bicubic=opt.bicubic, spans=True,
                                        window=BLOCK, frames=True)
    timings["line_pairs"] = time.perf_counter() - t0
    logger.info("line images %dx%d, parallax %d..%d columns", width, len(grid.phi), min_d, min_d + num_d)

    t0 = time.perf_counter()
    jump = opt.jump_penalty or choose_jump_penalty(L1, L2, num_d, opt)
    disp, full = _sgbm(L1, L2, min_d, num_d, opt.uniqueness, full_paths=opt.full_paths, speckle=opt.speckle,
                       jump=jump, speckle_share=_speckle_share(opt))
    halves = halve_line_images(L1, L2) if opt.half_fill or opt.half_check or opt.lr_check else None  # one copy
    n_half = n_off = n_lr = 0
    if opt.half_fill or opt.half_check:
        half = half_size_sgm(halves, num_d, jump, full, opt.uniqueness, opt.speckle, _speckle_share(opt))
        if opt.half_check:
            n_off = drop_off_half_size(disp, half, min_d, min_d - 1.0)
        if opt.half_fill:
            n_half = fill_from_half_size(disp, halves, half, min_d, min_d - 1.0)
        del half
    if opt.lr_check:
        n_lr = drop_left_right(disp, halves, min_d, num_d, jump, full, min_d - 1.0)
    del halves
    n_flat = drop_flat_windows(disp, L1, min_d - 1.0) if opt.flat_check else 0
    n_out = drop_outside_windows(disp, span2, min_d, min_d - 1.0) if opt.outside_check else 0
    n_col = drop_collisions(disp, L1, L2, min_d, min_d - 1.0) if opt.collision_check else 0
    plain = plain_windows(L1) if opt.plain_fit or opt.occlusion_check or opt.carried_check else None
    n_occ = drop_occluded_plain(disp, L1, plain, span2, min_d, min_d - 1.0) if opt.occlusion_check else 0
    n_car = drop_carried_plain(disp, L1, plain, min_d - 1.0) if opt.carried_check else 0
    del L1, L2
    far_end, near_end = lo + END_COLUMNS + 1, hi - END_COLUMNS - 1  # the range within its end columns
    n_far = drop_unseen_far(disp, span2, min_d, far_end, min_d - 1.0) if opt.far_check else 0
    if opt.far_surface_check:
        n_far += drop_unanchored_far(disp, span2, min_d, far_end, near_end, min_d - 1.0)
    n_ends = drop_range_ends(disp, min_d, min_d + num_d - 1, min_d - 1.0) if opt.end_check else 0
    n_near = 0
    if found is not None and opt.near_check:
        n_near = drop_unsupported_near(disp, grid, found, near, near_end, min_d - 1.0)
    n_frame = drop_frame_end_runs(disp, frames, min_d, min_d - 1.0) if opt.frame_check else 0
    n_fat = drop_fattened_cells(disp, min_d - 1.0) if opt.edge_check else 0
    if opt.median:
        surface_median(disp, min_d - 1.0, slanted=opt.slanted_median)
    n_fit = fit_plain_surfaces(disp, plain, min_d - 1.0) if opt.plain_fit else 0
    del plain
    n_dense = int(np.count_nonzero(disp >= min_d))
    # leading slices of pixel-sized arrays, so that the plane fill's matches (unmatched
    # pixels of image 1) append without copying the millions found (a few tenths of a
    # second on 2000x1500)
    uv1, uv2, X, rows = pixel_matches(disp, min_d, grid, tv, size1, size2, opt.interpolate)
    del disp
    n_sgm = len(uv1)
    n_planes = n_moved = n_scattered = 0
    if opt.planes or opt.plane_snap or opt.scattered_check:
        pf = fill_planes(to_gray(img1), size2, tv, uv1, uv2, X, fill=opt.planes, snap=opt.plane_snap,
                         drop=opt.scattered_check, rims=opt.rim_planes)
        n_planes, n_moved, n_scattered = len(pf.uv1), len(pf.moved), len(pf.dropped)
        uv2[pf.moved] = pf.moved_uv2
        X[pf.moved] = pf.moved_xyz
        if n_scattered:  # (none of them moved: their regions are not one plane)
            keep = np.ones(n_sgm, bool)
            keep[pf.dropped] = False
            uv1, uv2, X, rows = uv1[keep], uv2[keep], X[keep], rows[keep]
            n_sgm = len(uv1)
    if n_planes:
        # no line of the line images (-1), and a lower confidence than a match SGM found
        uv1, uv2, X = append_rows(uv1, pf.uv1), append_rows(uv2, pf.uv2), append_rows(X, pf.xyz)
        rows = append_rows(rows, np.full(n_planes, -1, rows.dtype))
    score = np.ones(len(uv1))
    score[n_sgm:] = PLANE_SCORE
    timings["matching"] = time.perf_counter() - t0
    counts = {
        "line_pairs": int(len(grid.phi)),
        "samples": int(len(grid.phi) * grid.columns),
        "rough_matches": 0,
        "dense_matches": n_dense,
        "valid_matches": int(len(uv1)),
        "jump_penalty": int(jump),  # SGM's P2 chosen for the pair (in units of C B^2)
    }
    logger.info("SGM (%s): %d line pairs, %d dense (%d of them from SGM at half size; %d off the sure estimates of "
                "SGM at half size, %d contradicted by SGM from image 2, %d more at the ends of the search, %d on "
                "windows without signal, %d on windows beyond image 2, %d sharing a pixel of image 2 with another "
                "surface, %d carried into an unmatched plain region, %d carried across a depth jump on a plain region, "
                "%d far where image 2 sees no nearer parallax or on a surface it sees nowhere at every one, %d near "
                "without a coarse surface there, %d in runs matching image 1's edge to image 2's and %d fattened at "
                "depth edges dropped), %d on plain windows fitted "
                "to their surface's plane, %d filled on plain planes and %d moved onto them, %d on plain regions "
                "mostly unmatched and on no one plane dropped, %d valid",
                "4 full paths" if full else "3 directions", counts["line_pairs"], n_dense, n_half, n_off, n_lr, n_ends,
                n_flat, n_out, n_col, n_occ, n_car, n_far, n_near, n_frame, n_fat, n_fit, n_planes, n_moved,
                n_scattered, len(uv1))
    return DenseMatches(uv1, uv2, score, rows, X, counts, timings)
