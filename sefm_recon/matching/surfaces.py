"""The disparities of the line images smoothed over each surface (after the checks).

A 5x5 median over each surface, about the window's plane where it lies on one
(:func:`surface_median`, :func:`local_planes`), and on plain windows (:func:`plain_windows`)
each disparity from its surface's local plane (:func:`fit_plain_surfaces`): on plain
windows SGM's winner is set by its smoothness penalties, a slanted plain surface comes out
as a staircase. Plain cells a column or two off a wider window's plane move onto it where
it matches image 2 as well (:func:`fit_wide_planes`): SGM's streaks along the lines are
longer than the local fit's window. ``disp`` is (rows, columns) float32 parallax in
columns, invalid at or below ``invalid``; each function changes it in place.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit, prange

from ..arrays import quiet_windows
from ..io.images import to_gray
from .stereo_sgbm import BLOCK

__all__ = ["anchored_cells", "fit_plain_surfaces", "fit_wide_planes", "local_planes", "plain_windows", "surface_forest",
           "surface_median", "surface_root"]

#: Neighbouring disparities within this many columns of the nearest cell's are on its
#: surface and are interpolated with it; others (across a depth edge) are left out. One
#: column is the left-right check's own tolerance (:data:`.stereo_sgbm.LR_MAX_DIFF`).
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
#: values over its :data:`.stereo_sgbm.BLOCK` square is below this many grey levels: the sensor noise of
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


#: SGM's errors on a plain surface run in streaks along the lines, 20-40 cells long and a few
#: rows tall, 1-3 columns off and centred on the surface (a generated floor of weak texture,
#: seed 13): longer than the plane fit's window, which takes a streak for the surface. Plain
#: cells are tried on the plane of a window this many cells each side (25 x 25 cells), where
#: the streaks of several rows average out.
WIDE_FIT_HALF = 12
#: ...where the window's estimates lie within this many columns (root mean square) of that
#: plane: the streaks' scatter (about a column) and no more; a step of 4 columns in the
#: window, or a surface curved by more, leaves more.
WIDE_FIT_RMS = 1.0
#: ...and only cells this many columns off the plane: one column, the precision a match is
#: judged at, up to two, where beyond a cell is another surface's (or a gross error, not a
#: streak). Cells within a column stay: on a curved surface the plane's own error is of that
#: order, and the matching cost cannot tell such shifts apart from its noise.
WIDE_FIT_MOVE = (1.0, 2.0)


@njit(cache=True)
def surface_root(parent, i):
    """The root of ``i`` in the union-find forest ``parent``, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True)
def surface_forest(disp, invalid, tol):
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
                    a, b = surface_root(parent, i), surface_root(parent, j)
                    if a != b:
                        parent[max(a, b)] = min(a, b)
    return parent


@njit(cache=True)
def anchored_cells(parent, anchor):
    """(n,) bool: the cells whose tree in ``parent`` holds a cell of ``anchor``."""
    n = len(parent)
    root = np.empty(n, np.int32)
    anchored = np.zeros(n, np.bool_)
    for i in range(n):
        root[i] = surface_root(parent, i)
        if anchor[i]:
            anchored[root[i]] = True
    out = np.empty(n, np.bool_)
    for i in range(n):
        out[i] = anchored[root[i]]
    return out


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
    """(rows, width) bool: the cells of line image 1 (colour, or its grey values) whose
    :data:`.stereo_sgbm.BLOCK` square window has a grey-value standard deviation below
    :data:`PLAIN_LEVELS` (:func:`fit_plain_surfaces`)."""
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


def fit_wide_planes(disp: np.ndarray, plain: np.ndarray, gray1: np.ndarray, gray2: np.ndarray, shift: int,
                    invalid: float) -> int:
    """Move each valid disparity of ``disp`` (rows, columns) float32 on a ``plain`` cell
    (:func:`plain_windows`), in place, onto the least-squares plane of its (2
    :data:`WIDE_FIT_HALF` + 1)-cell window where that window lies on one plane
    (:data:`WIDE_FIT_RMS`), the cell is :data:`WIDE_FIT_MOVE` columns off it, and the plane's
    disparity matches image 2 at least as well as the cell's own: the sum of squared
    differences of the grey values, less their means, over the :data:`.stereo_sgbm.BLOCK`
    square windows (``gray1``, ``gray2``: the (rows, columns) uint8 grey line images, image
    2's shifted by ``shift`` columns as SGM took it). Returns how many moved.

    A streak's cells move: its cost is as low on the plane as at SGM's winner, set there by
    the smoothness penalties. A relief the plane rounds off keeps its estimates: its windows
    match worse on the plane.
    """
    lo, hi = WIDE_FIT_MOVE
    plane, rms, _ = local_planes(disp, invalid, WIDE_FIT_HALF)
    off = cv2.absdiff(disp, plane)
    todo = plain & (disp > invalid) & (rms <= WIDE_FIT_RMS) & (off >= lo) & (off <= hi)
    rows, cols = np.nonzero(todo)
    better = _matches_better(gray1, gray2, rows, cols, disp, plane, float(shift), BLOCK // 2)
    rows, cols = rows[better], cols[better]
    disp[rows, cols] = plane[rows, cols]
    return len(rows)


@njit(parallel=True, cache=True)
def _matches_better(g1, g2, rows, cols, disp, plane, shift, half):
    """(n,) bool: whether the cells ``rows``, ``cols`` match image 2 at least as well at
    ``plane`` as at ``disp`` (zero-mean sums of squared differences over the (2 ``half`` + 1)
    square windows, image 2 read between columns linearly); False where a window leaves
    either line image."""
    n = len(rows)
    out = np.zeros(n, np.bool_)
    h, w = g1.shape
    for k in prange(n):
        r, c = rows[k], cols[k]
        if r < half or r >= h - half or c < half or c >= w - half:
            continue
        own = _zssd(g1, g2, r, c, disp[r, c] - shift, half)
        on = _zssd(g1, g2, r, c, plane[r, c] - shift, half)
        out[k] = on <= own
    return out


@njit(cache=True)
def _zssd(g1, g2, r, c, d, half):
    """The zero-mean sum of squared differences between ``g1``'s window about (``r``, ``c``)
    and ``g2``'s about (``r``, ``c - d``), read linearly between columns; infinity where that
    leaves ``g2``."""
    x = c - d
    j = int(math.floor(x))
    f = x - j
    if j - half < 0 or j + half + 1 >= g2.shape[1]:
        return np.inf
    sa = sb = saa = sbb = sab = 0.0
    for dr in range(-half, half + 1):
        for dc in range(-half, half + 1):
            a = float(g1[r + dr, c + dc])
            b = (1.0 - f) * g2[r + dr, j + dc] + f * g2[r + dr, j + dc + 1]
            sa += a
            sb += b
            saa += a * a
            sbb += b * b
            sab += a * b
    m = float((2 * half + 1) ** 2)
    return (saa - sa * sa / m) + (sbb - sb * sb / m) - 2.0 * (sab - sa * sb / m)
