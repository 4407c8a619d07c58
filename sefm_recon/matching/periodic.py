"""Estimates on texture that repeats along the lines, dropped where their surface has no other.

A texture periodic along the epipolar lines (stripes, planks, tiles) has a cost minimum at
every period, and SGM's aggregation settles patches of it a period off, one depth each,
which the uniqueness test, the left-right check and the half-size check pass alike. The
check at the coarse pass's scale (:func:`.sgm.drop_off_coarse`) catches them where the
stripes average away and the surface under them has texture of its own; a floor of fine
stripes and nothing else is plain at that scale, and held-out generated seeds 25, 48 and 52
kept such floors matched a period off (8-18 % of their matches over 3 px off).

Each cell of line image 1 gets a repeat score (:func:`repeat_score`): the highest ZNCC of
its window with the window ``s`` columns further along its row, over the shifts after the
ZNCC first fell to :data:`DIP_ZNCC` (a second peak of the autocorrelation, not the flank of
the first), tried over a pyramid up to the search's width (:data:`LEVEL_SHIFTS` shifts a
level). An estimate on a window that repeats (:data:`REPEAT_ZNCC`) is dropped where its
surface (cells joined along and across rows within :data:`.surfaces.SAME_SURFACE_COLUMNS`)
holds fewer than :data:`ANCHOR_SHARE` of cells on windows with texture that does not repeat
(below :data:`ONCE_ZNCC`): a surface with texture of its own was placed by that texture,
and its striped part with it; a patch of stripes alone could lie a period off. A patch a
period off that its surface's right part joins through a slanted floor, whose parallax runs
through the period from near to far, is kept with it (unseen seed 73's floor).
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit, prange

from .surfaces import SAME_SURFACE_COLUMNS, surface_forest, surface_root

__all__ = ["drop_repeating", "repeat_score"]

#: The window compared with its shifted copy: SGM's block height (:data:`.stereo_sgbm.BLOCK`)
#: across the lines and 2 x this + 1 columns along them. 25 columns hold several periods of
#: the stripes that mislead SGM and few chance resemblances of a random texture: over 5 x 9
#: windows a cloudy wall's ZNCC reached 0.9 at some shift in a fifth of its cells.
WINDOW_HALF = 12
WINDOW_ROWS = 5
#: A window repeats where its ZNCC with a shifted copy comes back to this after the dip:
#: a stripe pattern's windows correlate at 0.95-1.0 a period apart under the generated
#: scenes' noise; a random texture's rarely above 0.8.
REPEAT_ZNCC = 0.9
#: ...after first falling to this (uncorrelated or opposite: half a period of stripes), so
#: that a smooth texture's slow fall from 1 at the first shifts is no repeat.
DIP_ZNCC = 0.0
#: A textured window whose best later peak stays below this does not repeat, and anchors its
#: surface: the gap from :data:`REPEAT_ZNCC` leaves the cells in between to neither side.
ONCE_ZNCC = 0.7
#: A window whose grey values vary by less than this variance (2 grey levels standard
#: deviation, about the sensor noise) has no pattern to repeat and is neither.
MIN_VARIANCE = 4.0
#: Shifts tried at each level of the pyramid: 1 to this many columns at full size, then at
#: each halving those beyond half of it (periods of twice as many columns), until the shifts
#: reach the search's width. 16 columns at full size take the fine stripes that halving
#: blurs; the halvings keep the cost to about 1.3 x 16 shifts a cell.
LEVEL_SHIFTS = 16
#: The score is computed at every this many rows and columns (:func:`_score_level`).
STRIDE = 2
#: A surface is anchored by its cells on windows that do not repeat where they are at least
#: this share of its cells: the edges and blemishes of a striped patch are a few per cent.
ANCHOR_SHARE = 0.1


@njit(parallel=True, cache=True)
def _score_level(g, smin, smax, half, rows_w, min_var, dip):
    """One level of :func:`repeat_score` over the shifts ``smin``..``smax``: (rows, width)
    float32, the best ZNCC after the dip, -1 where none, -2 where the window is plain or
    reaches beyond the row. Computed at every :data:`STRIDE`-th row and column, each value
    standing for the cells up to the next (a window of 5 x 25 cells moves by a row or a
    column of it)."""
    rows, width = g.shape
    out = np.full((rows, width), -1.0, np.float32)
    cols = 2 * half + 1
    up = rows_w // 2
    for rb in prange((rows + STRIDE - 1) // STRIDE):
        r = rb * STRIDE
        r0, r1 = max(r - up, 0), min(r + up + 1, rows)
        n = (r1 - r0) * cols
        # running sums along the row of the window's column sums (values, squares, products)
        cs = np.zeros(width + 1)
        cq = np.zeros(width + 1)
        for x in range(width):
            a = 0.0
            b = 0.0
            for rr in range(r0, r1):
                a += g[rr, x]
                b += g[rr, x] * g[rr, x]
            cs[x + 1] = cs[x] + a
            cq[x + 1] = cq[x] + b
        mean = np.zeros(width)
        inv = np.zeros(width)  # 1 / standard deviation; 0: plain or beyond the row
        best = np.full(width, -1.0)
        for x in range(half, width - half):
            mean[x] = (cs[x + half + 1] - cs[x - half]) / n
            v = (cq[x + half + 1] - cq[x - half]) / n - mean[x] * mean[x]
            if v >= min_var:
                inv[x] = 1.0 / np.sqrt(v)
        dipped = np.zeros(width, np.bool_)
        cp = np.zeros(width + 1)
        colp = np.zeros(width, np.float32)
        for s in range(1, min(smax, width - 1) + 1):
            colp[:] = 0.0
            for rr in range(r0, r1):  # (along the row innermost: vectorised)
                for x in range(width - s):
                    colp[x] += g[rr, x] * g[rr, x + s]
            for x in range(width - s):
                cp[x + 1] = cp[x] + colp[x]
            for x in range(half, width - half - s, STRIDE):
                if inv[x] == 0.0 or inv[x + s] == 0.0:
                    continue
                z = ((cp[x + half + 1] - cp[x - half]) / n - mean[x] * mean[x + s]) * inv[x] * inv[x + s]
                if z <= dip:
                    dipped[x] = True
                elif dipped[x] and s >= smin and z > best[x]:
                    best[x] = z
        for x in range(width):
            xs = x - (x - half) % STRIDE if x >= half else -1  # the computed column standing for x
            if xs < 0 or x >= width - half or inv[xs] == 0.0:
                v = -2.0
            else:
                v = best[xs]
            for rr in range(r, min(r + STRIDE, rows)):
                out[rr, x] = v
    return out


def repeat_score(gray: np.ndarray, shifts: int) -> np.ndarray:
    """How strongly each cell's window of ``gray`` (rows, width) repeats along its row within
    ``shifts`` columns: (rows, width) float32, the best ZNCC (:data:`WINDOW_ROWS` x 2
    :data:`WINDOW_HALF` + 1 windows) at a shift after the ZNCC first fell to
    :data:`DIP_ZNCC`; -1 where it never came back, -2 where the window is plain (below
    :data:`MIN_VARIANCE`) or reaches beyond the row. Shifts beyond :data:`LEVEL_SHIFTS`
    are tried on halved copies (INTER_AREA), their scores read back at the nearest cell."""
    h, w = gray.shape
    # float32 about the mean grey value (centred, the products' sums over a window keep the
    # digits a ZNCC needs): half float64's memory; its time on the bench pair was the same
    # within the machine's noise
    level = np.asarray(gray, np.float32) - np.float32(np.mean(gray))
    score = None
    step, smin = 1, 1
    while True:
        smax = min(LEVEL_SHIFTS, -(-shifts // step))  # (a repeat beyond the search misleads no match)
        s = _score_level(level, smin, smax, WINDOW_HALF, WINDOW_ROWS, MIN_VARIANCE, DIP_ZNCC)
        if score is None:
            score = s
        else:  # a window plain at full size stays plain
            np.maximum(score, cv2.resize(s, (w, h), interpolation=cv2.INTER_NEAREST), out=score, where=score > -2)
        if LEVEL_SHIFTS * step >= shifts or min(level.shape) < 2 * WINDOW_ROWS:
            return score
        level = cv2.resize(level, ((level.shape[1] + 1) // 2, (level.shape[0] + 1) // 2), interpolation=cv2.INTER_AREA)
        step, smin = 2 * step, LEVEL_SHIFTS // 2 + 1


def drop_repeating(disp: np.ndarray, gray: np.ndarray, shifts: int, invalid: float) -> int:
    """Set the estimates of ``disp`` (rows, width) float32, invalid at or below ``invalid``,
    on windows of ``gray`` (line image 1, same shape) that repeat within ``shifts`` columns
    (the search's width) to ``invalid``, in place, where their surface is not anchored by
    texture that does not repeat (:data:`ANCHOR_SHARE`); returns how many."""
    score = repeat_score(gray, shifts)
    if not np.any((score >= REPEAT_ZNCC) & (disp > invalid)):  # (no forest to build)
        return 0
    return int(_drop_repeating(disp, score, float(invalid), SAME_SURFACE_COLUMNS, REPEAT_ZNCC, ONCE_ZNCC,
                               ANCHOR_SHARE))


@njit(cache=True)
def _drop_repeating(disp, score, invalid, tol, repeat, once, share):
    parent = surface_forest(disp, invalid, tol)
    n = disp.size
    total = np.zeros(n, np.int64)
    anchors = np.zeros(n, np.int64)
    for i in range(n):
        if disp.flat[i] > invalid:
            root = surface_root(parent, i)
            total[root] += 1
            if -2.0 < score.flat[i] < once:
                anchors[root] += 1
    dropped = 0
    for i in range(n):
        if disp.flat[i] > invalid and score.flat[i] >= repeat:
            root = surface_root(parent, i)
            if anchors[root] < share * total[root]:
                disp.flat[i] = invalid
                dropped += 1
    return dropped
