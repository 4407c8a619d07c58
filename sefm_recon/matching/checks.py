"""Checks on SGM's disparities over the line images: estimates that are not surfaces found.

Each ``drop_*`` sets the estimates it rejects to ``invalid``, in place, and returns how many:
at the ends of the search (:func:`drop_range_ends`), on windows reaching into an area of one
value (:func:`drop_flat_windows`) or beyond image 2 (:func:`drop_outside_windows`), the
nearer surface's cell at depth edges (:func:`drop_fattened_cells`), two surfaces reaching one
pixel of image 2 (:func:`drop_collisions`), far end estimates image 2 does not see
(:func:`drop_unseen_far`, :func:`drop_unanchored_far`), runs that match image 1's edge to
image 2's (:func:`drop_frame_end_runs`), and plain cells a nearer surface carries across an
occlusion or a depth jump (:func:`drop_occluded_plain`, :func:`drop_carried_plain`); and the
islands these checks leave under the speckle filter's window (:func:`speckle_islands`).
``disp`` is (rows, width) float32 parallax in columns, image 2's line image shifted by
``shift`` (a cell ``x`` of parallax ``d`` matches ``x - (d - shift)``), invalid at or below
``invalid``.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from numba import njit, prange

from .stereo_sgbm import BLOCK, LR_MAX_DIFF, SPECKLE_RANGE, speckle_window
from .surfaces import MEDIAN_SAME_SURFACE, PLAIN_LEVELS, SAME_SURFACE_COLUMNS, anchored_cells, surface_forest

__all__ = ["drop_carried_plain", "drop_collisions", "drop_fattened_cells", "drop_flat_windows", "drop_frame_end_runs",
           "drop_occluded_plain", "drop_outside_windows", "drop_range_ends", "drop_unanchored_far", "drop_unseen_far",
           "flat_windows", "speckle_islands"]


def speckle_islands(disp: np.ndarray, num_d: int, invalid: float, share: float | None = None) -> np.ndarray:
    """(rows, width) bool: the valid cells of ``disp`` in patches of one surface (4-neighbours
    within :data:`.stereo_sgbm.SPECKLE_RANGE` columns) smaller than the speckle filter's window
    for a search over ``num_d`` columns (:func:`.stereo_sgbm.speckle_window`, ``share``):
    OpenCV's speckle test, asked again of what the checks leave.

    OpenCV's filter judges SGM's own map; the checks after it drop cells from the patches it
    kept, and the plain fits and medians move others, so that a patch's remains can lie cut
    off from every other cell of its surface, as small as the islands the filter drops and
    as often a wrong minimum.
    """
    valid = disp > invalid
    # OpenCV's filter takes 16-bit disparities: parallax above ``invalid`` in 1/scale columns
    # (1/16 as SGM's own output, coarser only where the search's columns would not fit)
    scale = min(16.0, 32000.0 / max(float(np.max(disp, initial=invalid) - invalid), 1.0))
    fixed = disp - np.float32(invalid)  # (one float32 copy, worked on in place)
    fixed *= scale
    np.maximum(np.round(fixed, out=fixed), 1.0, out=fixed)
    fixed[~valid] = 0.0
    fixed = fixed.astype(np.int16)
    cv2.filterSpeckles(fixed, 0, speckle_window(*disp.shape, num_d, share), SPECKLE_RANGE * scale)
    return valid & (fixed == 0)


def drop_range_ends(disp: np.ndarray, lo: int, hi: int, invalid: float) -> int:
    """Set the disparities within one column of either end of the searched columns
    ``lo..hi`` to ``invalid``, in place; returns how many."""
    ends = (disp > invalid) & ((disp < lo + 1) | (disp > hi - 1))
    disp[ends] = invalid
    return int(np.count_nonzero(ends))


#: At a depth edge SGM's windows (:data:`.stereo_sgbm.BLOCK` columns) straddle both surfaces and the
#: nearer one, whose texture usually dominates, takes cells of the farther one: its
#: disparity runs past the edge ("fattening"), and the left-right check passes them, as both
#: directions fatten alike. The cells of the nearer side next to a jump of more than twice
#: the check's tolerance (:data:`.stereo_sgbm.LR_MAX_DIFF`) are dropped, this many: a window two
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
    """Set the disparities whose matching window (:data:`.stereo_sgbm.BLOCK` columns) in line image 2
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
    :data:`.sgm.END_COLUMNS`) to ``invalid``, in place, where the cell's matching window in
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
    before its :data:`.sgm.END_COLUMNS`) to ``invalid``, in place, where their surface (the
    valid cells joined through neighbours, along a row or across rows, within
    :data:`.surfaces.SAME_SURFACE_COLUMNS`) reaches no cell that image 2 sees at every parallax of
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

    A tie itself (within one column of the first disparity, ``shift``, which
    :func:`drop_range_ends` drops) neither joins a surface nor vouches for one: its cost
    had no minimum, so it says nothing of the depth. Zoom seed 35's plain floor tiles at the
    rim, whose partners lie 150-200 columns nearer and beyond image 2's edge, were ties at
    the far end joined through more ties to tiles image 2 sees (22,222 cells, 2,974 of them
    seen at every parallax, 2,664 of those ties), and kept 3,727 matches outside image 2's
    frame: 0.905 / 0.960 / 0.597 -> 0.931 / 0.987 / 0.597 (p@1 / p@3 / cov@1). No other seed
    of 0-79 moves by 0.002. The real walls and cloth at the rim are joined through estimates, not
    ties, but for Midd2 conv's wall (0.930 / 0.695 -> 0.923 / 0.688 at 1 px; the real means
    within 0.0001).

    ``disp`` (rows, width) float32 parallax in columns, invalid at or below ``invalid``;
    ``span2`` (rows, 2) and ``shift`` as for :func:`drop_outside_windows`.
    """
    first = _first_seen(span2, shift, near, disp.shape[1])
    return int(_drop_unanchored(disp, first, float(end), float(invalid), SAME_SURFACE_COLUMNS, float(shift + 1)))


@njit(cache=True)
def _drop_unanchored(disp, first, end, invalid, tol, tie):
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
    anchor = np.zeros(rows * width, np.bool_)  # the estimates image 2 sees at every parallax, ties left out
    for r in range(rows):
        for x in range(first[r], width):
            anchor[r * width + x] = disp[r, x] >= tie
    # the surfaces, joined through no tie: the forest of the cells at or above `tie`
    anchored = anchored_cells(surface_forest(disp, np.nextafter(tie, -np.inf), tol), anchor)
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
    :data:`.surfaces.MEDIAN_SAME_SURFACE` columns (another surface). A farther surface beside a nearer
    one leaves unmatched in image 1 the strip that the nearer hides in image 2, as wide as
    their parallax difference: where the gap is that wide (within :data:`.surfaces.MEDIAN_SAME_SURFACE`)
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
    cells at the start of a run that are plain (:func:`.surfaces.plain_windows`) and of the colour of
    the unmatched cell before the run, each channel within :data:`.surfaces.PLAIN_LEVELS` (the plain
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
    (:func:`.surfaces.plain_windows`); ``span2`` (rows, 2) image 2's first and last column per row
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
    nearer side's cells, walking away from the jump, that are plain (:func:`.surfaces.plain_windows`)
    and of the farther cell's colour (each channel within :data:`.surfaces.PLAIN_LEVELS`; the farther
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
    """(rows, width) bool: the cells of line image 1 whose matching window (:data:`.stereo_sgbm.BLOCK`
    square) holds a single value in every channel (:func:`drop_flat_windows`)."""
    # uint8 max - min over the window, then any channel's (OpenCV's or: numpy's max over
    # the channel axis took ten times as long)
    spread = cv2.morphologyEx(L1, cv2.MORPH_GRADIENT, np.ones((BLOCK, BLOCK), np.uint8))
    if spread.ndim == 3:
        spread = functools.reduce(cv2.bitwise_or, [spread[..., c] for c in range(spread.shape[2])])
    return spread == 0


def drop_flat_windows(disp: np.ndarray, L1: np.ndarray, invalid: float) -> int:
    """Set the disparities whose matching window (:data:`.stereo_sgbm.BLOCK` square) in line image 1
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
