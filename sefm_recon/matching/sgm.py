"""Semi-global matching over the polar line images (``dense.method = "sgm"``): the stage.

The paper's DP along one epipolar line (§4.4) is the single-path case of
semi-global matching over the rows of the line images (:mod:`.lines`). Here OpenCV's
StereoSGBM (:mod:`.stereo_sgbm`) aggregates the cost along several paths across
neighbouring lines, with its Birchfield-Tomasi cost on gradient-prefiltered images and
raw values (image 2's tones matched to image 1's first where they differ, :mod:`.tone`), a
uniqueness test and sub-pixel interpolation. This module
sets the search range from the parallax of the pose's SIFT inliers (:func:`search_range`),
extended towards the camera along the surfaces a coarse pass finds beyond them
(:func:`extend_near`), chooses the jump penalty per pair (:func:`choose_jump_penalty`),
runs SGM at full and half size (the half-size run fills and judges the full-size one, a
second one from image 2 is the left-right check) and calls the stages in order
(:func:`match_pair_sgm`): the checks that drop estimates which are no surface found
(:mod:`.checks`), the median and plane fit over each surface (:mod:`.surfaces`), the
read-back at every pixel of image 1 (:mod:`.readback`: one match a pixel, exactly on its
epipolar line, and its scene point), and the fill of plain planes (:mod:`.planes`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
from numba import njit, prange

from ..arrays import append_rows, keep_rows
from ..config import Config
from ..errors import InputError
from ..geometry.two_view import TwoView
from ..io.images import to_gray
from .checks import (drop_carried_plain, drop_collisions, drop_fattened_cells, drop_flat_windows, drop_frame_end_runs,
                     drop_occluded_plain, drop_outside_windows, drop_range_ends, drop_unanchored_far, drop_unseen_far,
                     flat_windows, speckle_islands)
from .dominant import move_onto_dominant_planes
from .lines import LineGrid, line_grid, line_images, match_parallax, pixel_grid
from .periodic import ONCE_ZNCC, REPEAT_ZNCC, drop_repeating, repeat_score
from .planes import SearchStart, fill_planes
from .readback import pixel_matches
from .sefm import DenseMatches, depth_range
from .stereo_sgbm import (BLOCK, JUMP_PENALTY, LR_MAX_DIFF, STEP_PENALTY, four_paths_fit, num_disparities,
                          sgbm_disparity, speckle_share_for)
from .surfaces import (SAME_SURFACE_COLUMNS, anchored_cells, fit_plain_surfaces, fit_wide_planes, plain_windows,
                       surface_forest, surface_median)
from .tone import apply_tone_curve, fit_tone_curve, matched_colours
from .zncc import zncc

logger = logging.getLogger(__name__)

__all__ = ["choose_jump_penalty", "coarse_parallax", "coarse_range", "CoarseParallax", "drop_left_right",
           "drop_off_coarse", "drop_off_half_size", "drop_unsupported_near", "every_parallax", "extend_near",
           "fill_from_half_size", "half_size_sgm", "halve_line_images", "jump_ladder", "match_pair_sgm",
           "parallax_columns", "search_range", "sift_parallax_columns", "widen_range"]

#: The left-right check's second SGM (from image 2 to image 1) runs on copies of the line
#: images reduced this many times on both axes, its tolerance :data:`.stereo_sgbm.LR_MAX_DIFF` columns
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
#: reduced windows (:data:`.stereo_sgbm.BLOCK` reduced cells, twice the full-size ones on the scene)
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
#: The jump penalty P2 is chosen per pair (:func:`choose_jump_penalty`): from OpenCV's 32 it
#: doubles or halves while that keeps more cells through SGM's own checks (uniqueness,
#: left-right, speckle, windows without signal, ends of the search), the penalty whose
#: disparities agree with themselves best. The real pairs and the generated scenes want
#: opposite smoothing: fixed at 16 the plain walls of Midd1 and Midd2 gain 0.04-0.08 of
#: precision and 0.06-0.10 of coverage at 1 px and the generated scenes lose 0.03 / 0.09;
#: fixed at 64 the generated scenes gain 0.02 / 0.05 and the real pairs lose 0.004 / 0.009
#: (results.md). Between :data:`.stereo_sgbm.STEP_PENALTY` (a jump no dearer than a step of one
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
#: The confidence (``DenseMatches.score``) of a match filled from a plane (:mod:`.planes`): below
#: SGM's own (1), so that the pose check tracks the matches SGM found first.
PLANE_SCORE = 0.5


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
    :func:`.checks.drop_range_ends`).

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
    lo, hi = np.percentile(match_parallax(grid, tv, tv.kp1, tv.kp2), [1, 99])
    return float(lo), float(hi)


def widen_range(lo: float, hi: float, margin: float) -> tuple[float, float]:
    """A parallax range found (SIFT inliers, or the coarse pass) widened into the search: by
    ``margin`` of its span and at least :data:`MARGIN_COLUMNS` on each side, then by
    :data:`END_COLUMNS` and one column more (whose estimates are dropped, :func:`.checks.drop_range_ends`)."""
    m = max(MARGIN_COLUMNS, margin * (hi - lo))
    return float(lo - m - END_COLUMNS - 1), float(hi + m + END_COLUMNS + 1)


def drop_left_right(disp: np.ndarray, halves: tuple[np.ndarray, np.ndarray] | None, shift: int, num_d: int,
                    jump: int, full_paths: bool, invalid: float, textured: np.ndarray | None = None) -> int:
    """The left-right check: set the disparities that a second SGM, from image 2 to image 1,
    contradicts to ``invalid``, in place; returns how many.

    The second SGM runs over the mirrored line images reduced :data:`LR_REDUCTION` times
    (the same penalties, ``jump`` and aggregation, ``full_paths``; no uniqueness test, no
    speckle filter: it is asked where each cell of image 2 matches best, not whether it is
    sure). An estimate of ``disp`` whose partner lies between two reduced cells of image 2
    is dropped where both of them hold a parallax more than :data:`.stereo_sgbm.LR_MAX_DIFF` reduced
    columns from its own: a cell matched onto a surface whose own match lies elsewhere (the
    aperture of stripes along the lines, a partner that image 2 does not see, a plain region
    matched by chance). Where neither holds one (beyond the second search) it stays.

    The second SGM's window fattens the nearer surface over the farther by up to half a
    block (:data:`.stereo_sgbm.BLOCK` // 2 reduced cells). So on a ``textured`` cell of
    image 1 ((rows, width) bool; default none) an estimate whose two cells both hold one
    nearer parallax (within the tolerance of each other) stays where, walking from either
    over the cells of that parallax, a cell within half a block beyond holds its own: the
    textured real pairs lost their cells beside the depth edges to the fattening (Cloth2
    rect: 0.9599 / 0.9376 -> 0.9609 / 0.9397 at 1 px, against SGBM's 0.9501 / 0.9662). It
    keeps too the first cells of a strip hidden in image 2, whose partners lie within half a
    block inside the nearer surface there (the lateral test pair: 11 cells); image 1's own
    map beside them does not tell them apart (the nearer parallax within the jump to their
    right: 2 of the 11, and half of Cloth2's gain lost). On plain cells the nearer runs are
    the second SGM's noise, and the matches they keep turn the plain regions' verdicts
    (Midd1 rect's wall: 0.9460 / 0.7582 -> 0.9270 / 0.7399 judged so everywhere).

    ``disp`` (rows, width) float32 parallax in columns, invalid at or below ``invalid``;
    ``halves`` the line images SGM matched, reduced (:func:`halve_line_images`; None: too
    small, nothing judged), image 2's shifted by ``shift`` columns (a cell ``x`` of parallax
    ``d`` matches ``x - (d - shift)`` in line image 2), searched over ``num_d`` columns.
    """
    f = LR_REDUCTION
    if halves is None:
        return 0
    r1, r2 = (np.ascontiguousarray(r[:, ::-1]) for r in halves)
    nd = num_disparities(num_d / f)
    back, _ = sgbm_disparity(r2, r1, 0, nd, 0, full_paths=full_paths, speckle=False, jump=jump)
    back = np.ascontiguousarray(back[:, ::-1])  # parallax of image 2's reduced cells, -1: none
    textured = np.zeros(disp.shape, np.bool_) if textured is None else textured
    return int(_drop_left_right(disp, back, float(shift), float(invalid), float(f), float(LR_MAX_DIFF), textured,
                                BLOCK // 2).sum())


@njit(parallel=True, cache=True)
def _drop_left_right(disp, back, shift, invalid, f, tol, textured, reach):
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
            if textured[r, x] and _beyond_fattening(back[rr], c0, d_r, tol, reach):
                continue
            disp[r, x] = invalid
            count[r] += 1
    return count


@njit(cache=True)
def _beyond_fattening(row, c0, d, tol, reach):
    """Whether, from the cell ``c0`` leftwards or ``c0 + 1`` rightwards of ``row`` (a reduced
    row of the second SGM's parallax, -1: none), over cells within ``tol`` of that cell's
    parallax, itself over ``tol`` above ``d`` (nearer), a cell at most ``reach`` cells
    beyond holds ``d`` within ``tol``: a nearer surface's fattening over the cell's own."""
    for step in (-1, 1):
        c = c0 if step < 0 else c0 + 1
        near = row[c]
        if not near > d + tol:
            continue
        for _ in range(reach):
            c += step
            if c < 0 or c >= row.shape[0]:
                break
            v = row[c]
            if v >= 0 and abs(v - d) <= tol:
                return True
            if not abs(v - near) <= tol:
                break
    return False


def dropped_estimates(before: np.ndarray, after: np.ndarray, invalid: float) -> np.ndarray:
    """The estimates a check dropped: ``before`` ((rows, width) float32, the disparities before
    it; changed in place and returned) where ``after`` no longer holds them, ``invalid``
    elsewhere (no second pixel-sized array)."""
    before[~(before > after)] = np.float32(invalid)
    return before


def repeating_drops(drops: np.ndarray, repeat: np.ndarray | None, invalid: float) -> np.ndarray | None:
    """Of the estimates a check dropped, ``drops`` ((rows, width) float32, ``invalid`` where it
    dropped none; changed in place), those on texture that repeats along the lines
    (``repeat``, :func:`.periodic.repeat_score`, at least :data:`.periodic.REPEAT_ZNCC`), the
    others set to ``invalid``; None where none is left (or there is no ``repeat``). There the
    left-right check's second SGM, at half size, can go a period off (a stripe of 8 columns
    is one of 4 there), and the dominant planes may give them back (:mod:`.dominant`);
    elsewhere its verdict stands (given back everywhere, the bench pair's drops that are no
    stripes asked the planes' halves test: 16 % more matching time, results.md)."""
    if repeat is None:
        return None
    drops[repeat < REPEAT_ZNCC] = np.float32(invalid)
    return drops if np.any(drops > invalid) else None


def halve_line_images(L1: np.ndarray, L2: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Copies of the line images ``L1``, ``L2`` reduced :data:`LR_REDUCTION` times on both axes
    (area average, cut to a multiple of it), for :func:`fill_from_half_size` and
    :func:`drop_left_right`; None where they would hold fewer lines or columns than a
    window (:data:`.stereo_sgbm.BLOCK`): nothing to match there."""
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
    ``speckle_share`` of the cells, :func:`.stereo_sgbm.speckle_window`), searching
    ``num_d`` full-size columns: (rows, width) of the reduced cells, float32 reduced columns
    of parallax from image 2's shifted line image, invalid below 0. A texture of low contrast
    (clouds, a mottled wall) carries little signal in a full-size window against the sensor
    noise; halved, its windows see twice the texture and half the noise."""
    if halves is None:
        return None
    r1, r2 = halves
    half, _ = sgbm_disparity(r1, r2, 0, num_disparities(num_d / LR_REDUCTION), uniqueness, full_paths=full_paths,
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
    :data:`.stereo_sgbm.JUMP_PENALTY` towards the better of half and twice it, by factors of two while
    each step keeps more than :data:`JUMP_MARGIN` more, within :data:`JUMP_MIN`..:data:`JUMP_MAX`."""
    jump = JUMP_PENALTY
    step = max((2.0, 0.5), key=lambda f: count(int(jump * f)))
    while JUMP_MIN <= jump * step <= JUMP_MAX and count(int(jump * step)) > (1 + JUMP_MARGIN) * count(jump):
        jump = int(jump * step)
    return jump


def _cells_kept(L1: np.ndarray, L2: np.ndarray, num_d: int, opt,
                reduction: int) -> tuple[Callable[[int], int], dict[int, int]]:
    """``(count, kept)``: ``count`` maps a jump penalty to the cells SGM keeps through ``opt``'s
    checks on copies of the line images reduced ``reduction`` times on both axes (each
    penalty run once); ``kept`` holds the counts run so far."""
    size = (L1.shape[1] // reduction, L1.shape[0] // reduction)
    s1, s2 = (cv2.resize(L, size, interpolation=cv2.INTER_AREA) for L in (L1, L2))
    nd = num_disparities(num_d / reduction)
    full = opt.full_paths and four_paths_fit(L1, num_d)  # (the aggregation the full-size run will use)
    flat = flat_windows(s1) if opt.flat_check else None  # the same for every penalty
    kept: dict[int, int] = {}

    def count(jump: int) -> int:
        if jump not in kept:
            disp, _ = sgbm_disparity(s1, s2, 0, nd, opt.uniqueness, full_paths=full, speckle=opt.speckle,
                                     jump=jump, speckle_share=speckle_share_for(opt))
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
    reduced twice as much: where half and twice :data:`.stereo_sgbm.JUMP_PENALTY` keep the same cells as
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
    textured: np.ndarray  #: (rows, columns) bool: the cell's window is not plain (:func:`.surfaces.plain_windows`)
    step: float  #: full-size columns per coarse column
    grid: LineGrid | None = None  #: the coarse line images' grid (None: no place given, :func:`extend_near` alone)
    #: the colours of the matched cells and their partners (:func:`.tone.matched_colours`), for the tone fit
    colours: tuple[np.ndarray, np.ndarray] | None = None
    #: (rows, columns) bool: the cell's window has no texture that repeats along its row at this
    #: scale (:func:`.periodic.repeat_score` under :data:`.periodic.ONCE_ZNCC`), for
    #: :func:`drop_off_coarse` (None: not scored, every cell counts)
    once: np.ndarray | None = None

    def _nearest(self, grid: LineGrid, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The coarse row nearest each row (``rows``) and the coarse column nearest each column
        (``cols``) of the full-size ``grid``; the columns may lie beyond the coarse line images."""
        g = self.grid
        r = np.round(np.interp(grid.phi[rows], g.phi, np.arange(len(g.phi)))).astype(np.intp)
        return r, np.round(g.column(grid.alpha(cols))).astype(np.intp)

    def at(self, grid: LineGrid, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(n,) the parallax at the coarse cell nearest each cell (``rows``, ``cols``) of
        the full-size ``grid``; NaN where none (beyond the coarse line images)."""
        r, c = self._nearest(grid, rows, cols)
        inside = (c >= 0) & (c < self.parallax.shape[1])
        out = np.full(len(rows), np.nan, np.float32)
        out[inside] = self.parallax[r[inside], c[inside]]
        return out

    def on_grid(self, grid: LineGrid, columns: int) -> np.ndarray:
        """(rows of ``grid``, ``columns``) float32: :meth:`at` for every cell, gathered per row
        and per column (the nearest coarse row depends on the row alone, the nearest coarse
        column on the column alone): :func:`drop_off_coarse` took 0.26 s a run on the bench
        pair's 3.6 million cells through :meth:`at`, 0.02 s through this."""
        r, c = self._nearest(grid, np.arange(len(grid.phi)), np.arange(columns))
        w = self.parallax.shape[1]
        c[(c < 0) | (c >= w)] = w  # beyond the coarse line images: the NaN column appended
        padded = np.concatenate([self.parallax, np.full((len(self.parallax), 1), np.nan, np.float32)], axis=1)
        return padded[r[:, None], c[None, :]]


def coarse_parallax(img1: np.ndarray, img2: np.ndarray, tv: TwoView, grid: LineGrid, cfg: Config,
                    lo: float, hi: float, *, repeats: bool = False) -> CoarseParallax | None:
    """The parallax (columns of ``grid``) SGM finds on reduced copies of the images when it
    searches parallax columns ``lo..hi``; None where it finds none. With ``repeats``, also
    which cells' windows have no texture that repeats along the lines there
    (:attr:`CoarseParallax.once`, for :func:`drop_off_coarse`).

    The images are reduced (area average) by the smallest power of two from 2 that brings
    their line images to at most :data:`COARSE_COLUMNS` columns; estimates at the ends of the
    coarse search are dropped (:func:`.checks.drop_range_ends`).
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
    num_d = num_disparities(hi / to_fine - min_d + 2)
    gc.pad = num_d + 1
    L1, L2 = line_images(small[0], small[1], tvc, gc, gc.pad + gc.columns + 1, shift2=min_d, bicubic=False)
    disp, _ = sgbm_disparity(L1, L2, min_d, num_d, cfg.sgm.uniqueness, speckle_share=speckle_share_for(cfg.sgm))
    drop_range_ends(disp, min_d, min_d + num_d - 1, min_d - 1.0)
    found = disp >= min_d
    if not found.any():
        return None
    logger.info("coarse pass (1/%d size) over parallax %.0f..%.0f columns", factor, lo, hi)
    once = repeat_score(L1, num_d) < ONCE_ZNCC if repeats else None
    return CoarseParallax(np.where(found, disp * np.float32(to_fine), np.float32(np.nan)), ~plain_windows(L1), to_fine,
                          gc, matched_colours(L1, L2, disp, min_d), once)


def match_tone(img2: np.ndarray, found: CoarseParallax) -> np.ndarray:
    """``img2`` through the tone curve fitted to the coarse pass's matched colours
    (:mod:`.tone`), where it is worth applying; else ``img2`` itself."""
    curve = fit_tone_curve(*found.colours) if found.colours is not None else None
    if curve is None or not curve.worth_applying:
        return img2
    logger.info("image 2's tones matched to image 1's (gain %s, power %s: %.1f levels on average)",
                np.round(curve.gain, 3).tolist(), np.round(curve.power, 3).tolist(), curve.mean_shift)
    return apply_tone_curve(img2, curve)


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
    along a row or across rows within one coarse column, :data:`.surfaces.SAME_SURFACE_COLUMNS`)
    that holds a textured one (:attr:`CoarseParallax.textured`)."""
    finite = np.isfinite(found.parallax)
    p = np.where(finite, found.parallax, -np.inf).astype(np.float32)
    parent = surface_forest(p, -np.inf, SAME_SURFACE_COLUMNS * found.step)
    return anchored_cells(parent, (found.textured & finite).ravel()).reshape(p.shape) & finite


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


#: Coarse to fine as a check at the coarse pass's scale (:func:`drop_off_coarse`): an estimate
#: is judged where the coarse pass is sure, every coarse cell of this square about its own
#: holding an estimate on a textured window whose texture does not repeat along the lines at
#: that scale, all within :data:`COARSE_CHECK_SPREAD` coarse columns of each other (one
#: surface at that scale: not a depth edge, which a coarse window fattens, nor a plain wall,
#: whose coarse estimates are ties, nor stripes or tiles, whose coarse estimates may be a
#: period off as well).
COARSE_CHECK_SQUARE = 3
COARSE_CHECK_SPREAD = 1.0
#: ...and dropped where it lies more than this many coarse columns plus
#: :data:`COARSE_CHECK_MARGIN` full-size columns from the coarse estimate: the nearest
#: coarse cell's own offset (half a coarse cell, and a surface sloping by up to a coarse
#: column across the square) twice over, and the full-size window's reach of 2 columns.
COARSE_CHECK_COLUMNS = 2.0
COARSE_CHECK_MARGIN = 2.0


def drop_off_coarse(disp: np.ndarray, grid: LineGrid, found: CoarseParallax, invalid: float) -> int:
    """Set the estimates of ``disp`` (rows, columns of ``grid``) far from the coarse pass's
    (``found``) where that is sure (:data:`COARSE_CHECK_SQUARE`, :data:`COARSE_CHECK_SPREAD`,
    :data:`COARSE_CHECK_COLUMNS`) to ``invalid``, in place; returns how many.

    A texture periodic along the lines (stripes, planks) has a cost minimum at every period,
    and SGM's aggregation settles patches of it a period off, one depth each, which the
    uniqueness test, the left-right check and the half-size check (at half size the stripes
    are still there) pass alike (unseen generated seed 24's striped wall: 11 % of its matches
    over 3 px off). At the coarse pass's scale (1/4 to 1/8) such stripes average away and the
    surface under them matches once. Measured (true pose, p@1 / p@3 / cov@1): seed 24 0.845 /
    0.888 / 0.565 -> 0.928 / 0.975 / 0.565; the real pairs unchanged within 0.002 of each
    pair's figures. Without the square's test, at depth edges and on plain walls, Midd1 conv
    lost 0.073 of coverage.

    Where the texture still repeats along the lines at the coarse scale (:attr:`CoarseParallax.once`
    false: fine stripes and tiles, which the area average aliases rather than removes, and
    stripes wide enough to stay), the coarse estimate has a minimum at every period too, and
    the check does not judge: on generated seed 92's fine striped floor it dropped 88,000
    estimates, the coarse one wrong and the full-size one right, and on seed 276's tiled floor
    28,000. Over seeds 0-299 (true pose, p@1 / p@3 / cov@1): 0.9417 / 0.9871 / 0.7779 ->
    0.9417 / 0.9871 / 0.7795, the real pairs unchanged (no case by 0.0005, either pose);
    seed 92 0.995 / 0.998 / 0.653 -> 0.997 / 0.999 / 0.824, seed 276 0.953 / 0.988 / 0.838
    -> 0.955 / 0.989 / 0.890, while seed 156's box top, wide stripes a period off that the
    coarse pass had placed right, fell from 0.970 to 0.953 at 3 px.
    """
    P = found.parallax
    finite = np.isfinite(P)
    square = np.ones((COARSE_CHECK_SQUARE, COARSE_CHECK_SQUARE), np.uint8)
    # (OpenCV's morphology leaves cells beyond the coarse line images out of the square)
    judged = finite & found.textured
    if found.once is not None:
        judged &= found.once
    every = cv2.erode(judged.astype(np.uint8), square).astype(bool)
    spread = cv2.subtract(cv2.dilate(np.where(finite, P, np.float32(-1e9)), square),
                          cv2.erode(np.where(finite, P, np.float32(1e9)), square))
    sure = every & (spread <= COARSE_CHECK_SPREAD * found.step)
    there = dataclasses.replace(found, parallax=np.where(sure, P, np.float32(np.nan))).on_grid(grid, disp.shape[1])
    with np.errstate(invalid="ignore"):  # NaN: not sure there, kept
        drop = (disp > invalid) & (np.abs(disp - there) > COARSE_CHECK_COLUMNS * found.step + COARSE_CHECK_MARGIN)
    disp[drop] = invalid
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
        found = coarse_parallax(img1, img2, tv, grid, cfg, lo, max(hi, nearest + END_COLUMNS + 1),
                                repeats=opt.coarse_check)
        if found is not None and opt.tone_match:
            img2 = match_tone(img2, found)
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
    num_d = num_disparities(hi - lo + 1)
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
    disp, full = sgbm_disparity(L1, L2, min_d, num_d, opt.uniqueness, full_paths=opt.full_paths,
                                speckle=opt.speckle, jump=jump, speckle_share=speckle_share_for(opt))
    halves = halve_line_images(L1, L2) if opt.half_fill or opt.half_check or opt.lr_check else None  # one copy
    n_half = n_off = n_lr = 0
    if opt.half_fill or opt.half_check:
        half = half_size_sgm(halves, num_d, jump, full, opt.uniqueness, opt.speckle, speckle_share_for(opt))
        if opt.half_check:
            n_off = drop_off_half_size(disp, half, min_d, min_d - 1.0)
        if opt.half_fill:
            n_half = fill_from_half_size(disp, halves, half, min_d, min_d - 1.0)
        del half
    gray1 = to_gray(L1)  # once, for the plain windows and the wide fit
    plain = (plain_windows(gray1) if opt.plain_fit or opt.wide_fit or opt.occlusion_check or opt.carried_check
             or opt.lr_check else None)
    lr_drops = None  # (the estimates the checks drop that the dominant planes may give back)
    if opt.lr_check:
        before = disp.copy() if opt.dominant_planes and opt.lr_restore else None
        n_lr = drop_left_right(disp, halves, min_d, num_d, jump, full, min_d - 1.0, textured=~plain)
        if n_lr and before is not None:
            lr_drops = dropped_estimates(before, disp, min_d - 1.0)
        del before
    del halves
    n_flat = drop_flat_windows(disp, L1, min_d - 1.0) if opt.flat_check else 0
    n_out = drop_outside_windows(disp, span2, min_d, min_d - 1.0) if opt.outside_check else 0
    n_col = drop_collisions(disp, L1, L2, min_d, min_d - 1.0) if opt.collision_check else 0
    repeat = repeat_score(L1, num_d, frames[0][:, 1]) if opt.repeat_check else None  # (of the colours SGM matched)
    if lr_drops is not None:
        lr_drops = repeating_drops(lr_drops, repeat, min_d - 1.0)
    n_occ = drop_occluded_plain(disp, L1, plain, span2, min_d, min_d - 1.0) if opt.occlusion_check else 0
    n_car = drop_carried_plain(disp, L1, plain, min_d - 1.0) if opt.carried_check else 0
    gray2 = to_gray(L2) if opt.wide_fit else None
    del L1, L2
    far_end, near_end = lo + END_COLUMNS + 1, hi - END_COLUMNS - 1  # the range within its end columns
    n_far = drop_unseen_far(disp, span2, min_d, far_end, min_d - 1.0) if opt.far_check else 0
    if opt.far_surface_check:
        n_far += drop_unanchored_far(disp, span2, min_d, far_end, near_end, min_d - 1.0)
    n_ends = drop_range_ends(disp, min_d, min_d + num_d - 1, min_d - 1.0) if opt.end_check else 0
    n_near = 0
    if found is not None and opt.near_check:
        n_near = drop_unsupported_near(disp, grid, found, near, near_end, min_d - 1.0)
    n_coarse = drop_off_coarse(disp, grid, found, min_d - 1.0) if found is not None and opt.coarse_check else 0
    n_rep, repeats = 0, None
    if opt.repeat_check:
        restore = opt.dominant_planes and opt.repeat_restore
        before = disp.copy() if opt.scattered_check or restore else None
        n_rep = drop_repeating(disp, repeat, min_d - 1.0, frames[0])
        # the estimates dropped, for their plain regions' verdict (fill_planes) and the dominant
        # planes (given back where one bears them out)
        if n_rep and before is not None:
            repeats = dropped_estimates(before, disp, min_d - 1.0)
        del before
    n_frame = drop_frame_end_runs(disp, frames, min_d, min_d - 1.0) if opt.frame_check else 0
    n_fat = drop_fattened_cells(disp, min_d - 1.0) if opt.edge_check else 0
    if opt.median:
        surface_median(disp, min_d - 1.0, slanted=opt.slanted_median)
    n_fit = fit_plain_surfaces(disp, plain, min_d - 1.0) if opt.plain_fit else 0
    n_wide = fit_wide_planes(disp, plain, gray1, gray2, min_d, min_d - 1.0) if opt.wide_fit else 0
    del plain, gray1, gray2, repeat
    n_dense = int(np.count_nonzero(disp >= min_d))
    # judged here, dropped after the plane fill: a plain region's islands are part of what
    # SGM found there, for its verdict, and one moved onto the region's plane is the plane's
    islands = speckle_islands(disp, num_d, min_d - 1.0, speckle_share_for(opt)) if opt.speckle_after else None
    # the dropped estimates read back (before the matches, so that their pixel-sized arrays are
    # not held at once): the repeat check's for the plane fill's verdict, and with the left-right
    # check's as the dominant planes' candidates
    given = repeats if opt.dominant_planes and opt.repeat_restore else None
    if lr_drops is not None:
        given = lr_drops if given is None else np.maximum(given, lr_drops)  # (disjoint cells)
    del lr_drops
    candidates = scattered = None
    if given is not None:
        candidates = tuple(a.copy() for a in pixel_matches(given, min_d, grid, tv, size1, size2, opt.interpolate))
    if repeats is not None and opt.scattered_check:
        scattered = (candidates[:2] if given is repeats else
                     tuple(a.copy() for a in pixel_matches(repeats, min_d, grid, tv, size1, size2, opt.interpolate)[:2]))
    del given, repeats
    # leading slices of pixel-sized arrays, so that the plane fill's matches (unmatched
    # pixels of image 1) append without copying the millions found (a few tenths of a
    # second on 2000x1500)
    uv1, uv2, X, cells = pixel_matches(disp, min_d, grid, tv, size1, size2, opt.interpolate)
    drop = islands.ravel()[cells] if islands is not None else np.zeros(len(uv1), bool)
    rows = cells  # each match's row of the line images, in place (a leading slice still)
    n_cols = disp.shape[1]
    rows //= n_cols
    del disp, islands, cells
    n_sgm = len(uv1)
    n_planes = n_moved = n_scattered = 0
    filled = opt.planes or opt.plane_snap or opt.scattered_check
    # (for the plane fill and the dominant planes, where either runs)
    image1_gray = to_gray(img1) if filled or opt.dominant_planes else None
    image2_gray = to_gray(img2) if (filled and opt.aligned_planes) or opt.dominant_planes else None
    if filled:
        pf = fill_planes(image1_gray, size2, tv, uv1, uv2, X, fill=opt.planes, snap=opt.plane_snap,
                         drop=opt.scattered_check, rims=opt.rim_planes, borrow=opt.borrowed_planes,
                         two=opt.two_surfaces,
                         repeats=scattered,
                         start=SearchStart(grid, float(min_d)) if opt.scattered_check else None,
                         gray2=image2_gray if opt.aligned_planes else None)
        n_planes, n_moved, n_scattered = len(pf.uv1), len(pf.moved), len(pf.dropped)
        uv2[pf.moved] = pf.moved_uv2
        X[pf.moved] = pf.moved_xyz
        drop[pf.moved] = False
        drop[pf.dropped] = True  # (none of them moved: a region's moves are of matches on its plane)
    n_islands = int(np.count_nonzero(drop)) - n_scattered
    if n_islands or n_scattered:
        uv1, uv2, X, rows = keep_rows(~drop, uv1, uv2, X, rows)
        n_sgm = len(uv1)
    del drop
    if n_planes:
        # no line of the line images (-1), and a lower confidence than a match SGM found
        uv1, uv2, X = append_rows(uv1, pf.uv1), append_rows(uv2, pf.uv2), append_rows(X, pf.xyz)
        rows = append_rows(rows, np.full(n_planes, -1, rows.dtype))
    n_dominant = n_restored = 0
    if opt.dominant_planes:
        if candidates is not None:  # (those on a pixel the plane fill took stay out)
            free = np.ones(size1[::-1], bool)
            free[uv1[:, 1].astype(np.int64), uv1[:, 0].astype(np.int64)] = False
            c1, c2, cX, c_cells = candidates
            keep = free[c1[:, 1].astype(np.int64), c1[:, 0].astype(np.int64)]
            candidates = (c1[keep], c2[keep], cX[keep])
            c_rows = c_cells[keep] // n_cols
            del free, keep, c1, c2, cX, c_cells
        dm = move_onto_dominant_planes(image1_gray, image2_gray, tv, uv1, uv2, X, candidates=candidates)
        uv2[dm.moved], X[dm.moved] = dm.uv2, dm.xyz
        n_dominant, n_restored = len(dm.moved), len(dm.restored)
        if n_restored:  # (SGM's own estimates: a match's confidence)
            uv1, uv2 = append_rows(uv1, candidates[0][dm.restored]), append_rows(uv2, dm.restored_uv2)
            X, rows = append_rows(X, dm.restored_xyz), append_rows(rows, c_rows[dm.restored])
    score = np.ones(len(uv1))
    score[n_sgm:n_sgm + n_planes] = PLANE_SCORE
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
                "without a coarse surface there, %d far from the coarse pass's sure estimates, %d on texture repeating "
                "along the lines on surfaces without other texture, %d in runs matching image 1's edge to image 2's "
                "and %d fattened at depth edges dropped), %d on plain windows fitted to their surface's plane "
                "and %d moved onto a wider window's plane, %d filled on plain planes and %d moved onto them, %d on "
                "plain regions mostly unmatched and on no one plane (or off theirs on no second one, or on the ties at the "
                "search's first parallax) dropped, %d in islands under the speckle filter's window dropped, %d moved "
                "onto the largest aligned planes and %d dropped by the left-right or repeat check given back on them, %d valid",
                "4 full paths" if full else "3 directions", counts["line_pairs"], n_dense, n_half, n_off, n_lr, n_ends,
                n_flat, n_out, n_col, n_occ, n_car, n_far, n_near, n_coarse, n_rep, n_frame, n_fat, n_fit, n_wide,
                n_planes, n_moved, n_scattered, n_islands, n_dominant, n_restored, len(uv1))
    return DenseMatches(uv1, uv2, score, rows, X, counts, timings)

