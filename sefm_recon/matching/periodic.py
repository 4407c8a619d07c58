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
level). Where those copies ahead reach past image 1's edge within the shifts, the copies
behind are scored too: the stripes cannot come back beyond the image, and scored ahead
alone, the windows at the end of unseen seed 204's striped floor, at image 1's edge,
counted as texture that does not repeat and anchored a patch of it matched a period off.
(Everywhere both ways, a striped box face lost the windows at its edge, whose copies ahead
take in what lies beyond the stripes: that is texture that does not repeat, and it placed
the face.) An estimate on a window that repeats (:data:`REPEAT_ZNCC`) is dropped where its
surface (cells joined along and across rows within :data:`.surfaces.SAME_SURFACE_COLUMNS`)
holds fewer than :data:`ANCHOR_SHARE` of cells on windows with texture that does not repeat
(below :data:`ONCE_ZNCC`) and that lie on it (within image 1, the cells at both ends of the
window's row on the surface or without an estimate): a surface with texture of its own was
placed by that texture, and its striped part with it; a patch of stripes alone could lie a
period off. A window that reaches across a depth jump into another surface, or past the
image's edge, takes in texture that is not the surface's own: a patch of unseen seed 73's
striped floor, between a textured box and the image's edge, was matched 90 px off and
anchored by the windows at its two ends. Unanchored, a surface goes whole where most of its
cells repeat (:data:`MOSTLY_REPEATING`), the cells at its ends with it. (Cells without an
estimate hold no other surface: a fragmented striped floor's windows reach them, and
counted as no anchors, unseen zoom seed 59 lost 0.065 of coverage at 1 px, seed 43 with
its own pose 0.077.) A patch a period off that its surface's right part joins through a
slanted floor, whose parallax runs through the period from near to far, is kept with it.

SGM matches the colour line images, so stripes of two colours of one brightness mislead
it as much as grey stripes do, while their grey values hold only the sensor noise. Each
window is also scored on its chroma (the colour less its grey value), and repeats where
either repeats.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit, prange

from ..io.images import to_gray
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
#: The chroma: image 1's colour less its grey value (BT.601 weights, as ``cv2.COLOR_RGB2GRAY``)
#: in each of R, G and B, scaled by 1 / sqrt(3) (its variance the mean of the three). The three
#: channels span a plane (a grey pixel has none); these two rows give every sum of squares
#: and products over a window that the three give, in two passes of the ZNCC instead of
#: three. Unseen generated seed 89's red and green floor stripes vary by 2.5 grey levels over
#: 5 x 5 px, its sensor noise, and by 30 levels in red: in grey its windows were texture that
#: does not repeat and anchored the floor, which SGM matched a period off (0.806 of the
#: pair's matches within 3 px).
_GREY_WEIGHTS = np.array([0.299, 0.587, 0.114])
_CHROMA = (np.eye(3) - np.outer(np.ones(3), _GREY_WEIGHTS)) / np.sqrt(3.0)  # rows: R, G, B less grey


def _chroma_rows() -> np.ndarray:
    """(2, 3) float32 rows ``A`` with ``|A c|^2 = |_CHROMA c|^2`` for every colour ``c``."""
    lam, vec = np.linalg.eigh(_CHROMA.T @ _CHROMA)  # (rank 2: the first eigenvalue is 0)
    return (np.sqrt(lam[1:])[:, None] * vec[:, 1:].T).astype(np.float32)


_CHROMA_ROWS = _chroma_rows()
#: :data:`MIN_VARIANCE` for the chroma's two channels together: the same sensor noise, equal
#: and independent in R, G and B, has 0.780 of a channel's variance there (the sum of the
#: squared entries of :data:`_CHROMA`) against 0.447 in the grey values (of the squared weights).
MIN_CHROMA_VARIANCE = MIN_VARIANCE * float(np.sum(_CHROMA**2) / np.sum(_GREY_WEIGHTS**2))
#: Shifts tried at each level of the pyramid: 1 to this many columns at full size, then at
#: each halving those beyond half of it (periods of twice as many columns), until the shifts
#: reach the search's width. 16 columns at full size take the fine stripes that halving
#: blurs; the halvings keep the cost to about 1.3 x 16 shifts a cell.
LEVEL_SHIFTS = 16
#: The score is computed at every this many rows and columns (:func:`_score_level`).
STRIDE = 2
#: A surface is anchored by its cells on windows that do not repeat and lie on it where they
#: are at least this share of its cells: the blemishes of a striped patch are a few per cent.
ANCHOR_SHARE = 0.1
#: An unanchored surface more than this share of whose cells repeat goes whole: it was placed
#: by its stripes, and its other cells (windows at its ends, between the two scores) with
#: them. Below it, a surface of mostly other cells (plain, a few stripes) keeps those.
MOSTLY_REPEATING = 0.5


@njit(parallel=True, cache=True)
def _score_level(g, smin, smax, half, rows_w, min_var, dip, last):
    """One level of :func:`repeat_score` of ``g`` (channels, rows, width) float32 over the
    shifts ``smin``..``smax``: (rows, width) float32, the best ZNCC after the dip (the
    channels' covariances and variances summed) with the copy ahead or, past the column
    whose copies ahead reach ``last[r]`` (each row's last column within the image), after its
    own dip, the copy behind; -1 where none, -2 where the window is plain or reaches beyond
    the row. Computed at every :data:`STRIDE`-th row and column, each value
    standing for the cells up to the next (a window of 5 x 25 cells moves by a row or a
    column of it)."""
    nc, rows, width = g.shape
    out = np.full((rows, width), -1.0, np.float32)
    cols = 2 * half + 1
    up = rows_w // 2
    for rb in prange((rows + STRIDE - 1) // STRIDE):
        r = rb * STRIDE
        r0, r1 = max(r - up, 0), min(r + up + 1, rows)
        n = (r1 - r0) * cols
        # running sums along the row of the window's column sums (values, squares, products)
        cs = np.zeros((nc, width + 1))
        cq = np.zeros(width + 1)
        colq = np.zeros(width)
        for c in range(nc):
            cola = np.zeros(width)
            for rr in range(r0, r1):  # (along the row innermost: vectorised)
                row = g[c, rr]
                for x in range(width):
                    cola[x] += row[x]
                    colq[x] += row[x] * row[x]
            for x in range(width):
                cs[c, x + 1] = cs[c, x] + cola[x]
        for x in range(width):
            cq[x + 1] = cq[x] + colq[x]
        mean = np.zeros((nc, width))
        inv = np.zeros(width)  # 1 / standard deviation; 0: plain or beyond the row
        best = np.full(width, -1.0)
        for x in range(half, width - half):
            v = (cq[x + half + 1] - cq[x - half]) / n
            for c in range(nc):
                mean[c, x] = (cs[c, x + half + 1] - cs[c, x - half]) / n
                v -= mean[c, x] * mean[c, x]
            if v >= min_var:
                inv[x] = 1.0 / np.sqrt(v)
        if not np.any(inv):  # every window plain: no shift to try
            out[r:min(r + STRIDE, rows)] = -2.0
            continue
        dipped = np.zeros(width, np.bool_)
        # the windows past column `ahead` have copies ahead that reach beyond image 1's frame (or
        # the row) before the level's last shift: they are also scored on their copies behind,
        # from the first computed column past it
        ahead = min(last[r], width - 1) - half - min(smax, width - 1)
        first_back = half if ahead < half else half + ((ahead - half) // STRIDE + 1) * STRIDE
        dipped_l = np.zeros(width, np.bool_)  # (as `dipped`, the copies behind)
        best_l = np.full(width, -1.0)
        cp = np.zeros(width + 1)
        colp = np.zeros(width, np.float32)
        mm = np.zeros(width)
        for s in range(1, min(smax, width - 1) + 1):
            colp[:] = 0.0
            for c in range(nc):
                for rr in range(r0, r1):  # (along the row innermost: vectorised)
                    row = g[c, rr]
                    for x in range(width - s):
                        colp[x] += row[x] * row[x + s]
            for x in range(width - s):
                cp[x + 1] = cp[x] + colp[x]
            # the windows' means' products summed over the channels, kept out of the loop
            # below (a loop over the channels inside it slowed the kernel by a fifth)
            mm[:] = 0.0
            for c in range(nc):
                mc = mean[c]
                for x in range(half, width - half - s):
                    mm[x] += mc[x] * mc[x + s]
            for x in range(half, width - half - s, STRIDE):
                if inv[x] == 0.0 or inv[x + s] == 0.0:
                    continue
                z = ((cp[x + half + 1] - cp[x - half]) / n - mm[x]) * inv[x] * inv[x + s]
                if z <= dip:
                    dipped[x] = True
                elif dipped[x] and s >= smin and z > best[x]:
                    best[x] = z
            # the window at y against its copy s columns back (the ZNCC of the windows at y - s and y)
            for y in range(max(first_back, half + -(-s // STRIDE) * STRIDE), width - half, STRIDE):
                x = y - s
                if inv[x] == 0.0 or inv[y] == 0.0:
                    continue
                z = ((cp[x + half + 1] - cp[x - half]) / n - mm[x]) * inv[x] * inv[y]
                if z <= dip:
                    dipped_l[y] = True
                elif dipped_l[y] and s >= smin and z > best_l[y]:
                    best_l[y] = z
        for x in range(width):
            xs = x - (x - half) % STRIDE if x >= half else -1  # the computed column standing for x
            if xs < 0 or x >= width - half or inv[xs] == 0.0:
                v = -2.0
            else:
                v = max(best[xs], best_l[xs])  # (best_l is -1 up to `ahead`)
            for rr in range(r, min(r + STRIDE, rows)):
                out[rr, x] = v
    return out


def repeat_score(image: np.ndarray, shifts: int, last: np.ndarray | None = None) -> np.ndarray:
    """How strongly each cell's window of ``image`` (rows, width) grey or (rows, width, 3) RGB
    repeats along its row within ``shifts`` columns: (rows, width) float32, the best ZNCC
    (:data:`WINDOW_ROWS` x 2 :data:`WINDOW_HALF` + 1 windows) at a shift after the ZNCC first
    fell to :data:`DIP_ZNCC`, of its copies ahead and, where those reach past ``last`` ((rows,)
    int64, each row's last column within image 1; default the row's end) within the shifts,
    of its copies behind too; -1 where it never came back, -2 where the window is plain (below
    :data:`MIN_VARIANCE`) or reaches beyond the row. Shifts beyond :data:`LEVEL_SHIFTS` are
    tried on halved copies (INTER_AREA), their scores read back at the nearest cell. Of a
    colour image, the higher of its grey values' score and its chroma's (:data:`_CHROMA`,
    plain below :data:`MIN_CHROMA_VARIANCE`): -2 where both are plain."""
    h, w = image.shape[:2]
    last = np.full(h, w - 1, np.int64) if last is None else np.asarray(last, np.int64)
    if image.ndim == 2:
        # (a copy: centred in place)
        return _repeat_score(np.array(image, np.float32)[None], shifts, MIN_VARIANCE, last)
    score = _repeat_score(to_gray(image).astype(np.float32)[None], shifts, MIN_VARIANCE, last)
    chroma = (image.reshape(h * w, 3).astype(np.float32) @ _CHROMA_ROWS.T).T.reshape(2, h, w)
    return np.maximum(score, _repeat_score(chroma, shifts, MIN_CHROMA_VARIANCE, last), out=score)


def _repeat_score(level: np.ndarray, shifts: int, min_var: float, last: np.ndarray) -> np.ndarray:
    """:func:`repeat_score` of the channels ``level`` (channels, rows, width) float32 together
    (centred here, in place), a window plain where their variances sum to less than ``min_var``;
    ``last`` (rows,) int64 each row's last column within image 1."""
    _, h, w = level.shape
    # about each channel's mean (centred, the float32 products' sums over a window keep the
    # digits a ZNCC needs): half float64's memory; its time on the bench pair was the same
    # within the machine's noise
    for plane in level:
        plane -= np.float32(np.mean(plane, dtype=np.float64))
    score = None
    step, smin = 1, 1
    while True:
        smax = min(LEVEL_SHIFTS, -(-shifts // step))  # (a repeat beyond the search misleads no match)
        # each reduced row's last column within image 1: that of the rows it averages, the least
        ends = np.minimum.reduceat(last, np.arange(0, h, step)) // step
        s = _score_level(np.ascontiguousarray(level), smin, smax, WINDOW_HALF, WINDOW_ROWS, min_var, DIP_ZNCC, ends)
        if score is None:
            score = s
        else:  # the nearest cell's score where higher; a window plain at full size stays plain
            _raise_to(score, s, _nearest(h, s.shape[0]), _nearest(w, s.shape[1]))
        if LEVEL_SHIFTS * step >= shifts or min(level.shape[1:]) < 2 * WINDOW_ROWS:
            return score
        size = ((level.shape[2] + 1) // 2, (level.shape[1] + 1) // 2)
        level = np.stack([cv2.resize(p, size, interpolation=cv2.INTER_AREA) for p in level])
        step, smin = 2 * step, LEVEL_SHIFTS // 2 + 1


def _nearest(n: int, m: int) -> np.ndarray:
    """(n,) int64: the index among ``m`` that OpenCV's INTER_NEAREST reads for each of ``n``."""
    ramp = np.arange(m, dtype=np.float32)[None]
    return cv2.resize(ramp, (n, 1), interpolation=cv2.INTER_NEAREST)[0].astype(np.int64)


@njit(parallel=True, cache=True)
def _raise_to(score, coarse, rows, cols):
    """``score`` (h, w) raised, in place, to ``coarse[rows[r], cols[c]]`` where that is higher
    and ``score`` is not -2 (plain): a nearest-neighbour upsampling and maximum in one pass."""
    for r in prange(score.shape[0]):
        src = coarse[rows[r]]
        for c in range(score.shape[1]):
            v = src[cols[c]]
            if v > score[r, c] > -2.0:
                score[r, c] = v


def drop_repeating(disp: np.ndarray, score: np.ndarray, invalid: float, frame: np.ndarray | None = None) -> int:
    """Set the estimates of ``disp`` (rows, width) float32, invalid at or below ``invalid``,
    on windows that repeat (``score``: :func:`repeat_score` of line image 1 within the
    search's width) to ``invalid``, in place, where their surface is not anchored by
    texture of its own that does not repeat (:data:`ANCHOR_SHARE`: windows whose row lies
    within image 1's ``frame``, (rows, 2) int64 each row's first and last column in the
    image, default the whole row, and ends on the surface or on a cell without an
    estimate), and every estimate of such a surface that mostly repeats
    (:data:`MOSTLY_REPEATING`); returns how many."""
    if not np.any((score >= REPEAT_ZNCC) & (disp > invalid)):  # (no forest to build)
        return 0
    if frame is None:
        frame = np.tile(np.array([0, disp.shape[1] - 1], np.int64), (disp.shape[0], 1))
    return int(_drop_repeating(disp, score, float(invalid), np.ascontiguousarray(frame, np.int64),
                               SAME_SURFACE_COLUMNS, REPEAT_ZNCC, ONCE_ZNCC, ANCHOR_SHARE, MOSTLY_REPEATING,
                               WINDOW_HALF))


@njit(cache=True)
def _on_surface_or_none(disp, parent, j, invalid, root):
    """Whether cell ``j`` has no estimate or lies on the surface of ``root``."""
    return disp.flat[j] <= invalid or surface_root(parent, j) == root


@njit(cache=True)
def _drop_repeating(disp, score, invalid, frame, tol, repeat, once, share, mostly, half):
    parent = surface_forest(disp, invalid, tol)
    n = disp.size
    width = disp.shape[1]
    total = np.zeros(n, np.int64)
    anchors = np.zeros(n, np.int64)
    repeating = np.zeros(n, np.int64)
    for i in range(n):
        if disp.flat[i] > invalid:
            root = surface_root(parent, i)
            total[root] += 1
            if score.flat[i] >= repeat:
                repeating[root] += 1
            r, x = i // width, i % width
            # an anchor's window lies in the image and on its surface: its row's end cells
            # on it or without an estimate, not on another surface (:func:`drop_repeating`)
            if (-2.0 < score.flat[i] < once and x - half >= frame[r, 0] and x + half <= frame[r, 1]
                    and _on_surface_or_none(disp, parent, i - half, invalid, root)
                    and _on_surface_or_none(disp, parent, i + half, invalid, root)):
                anchors[root] += 1
    dropped = 0
    for i in range(n):
        if disp.flat[i] > invalid:
            root = surface_root(parent, i)
            if anchors[root] < share * total[root] and (score.flat[i] >= repeat
                                                         or repeating[root] > mostly * total[root]):
                disp.flat[i] = invalid
                dropped += 1
    return dropped
