"""OpenCV's StereoSGBM over the polar line images: its settings and the call.

The matcher's semi-global matching (:mod:`.sgm`) runs OpenCV's StereoSGBM over the rows of
the line images (:mod:`.lines`) with the evaluation's SGBM peer's settings (5x5 blocks,
P1 = 8 C B^2, the jump penalty P2 chosen per pair, a uniqueness test, a speckle filter):
four full aggregation paths, over strips of rows where the whole cost volume does not fit.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["four_paths_fit", "num_disparities", "sgbm_disparity", "speckle_share_for", "speckle_window", "strip_rows",
           "volume_fits"]

#: StereoSGBM's settings, those of the evaluation's planar SGBM peer: 5x5 blocks, OpenCV's
#: recommended smoothness penalties P1 = 8 C B^2 and P2 = 32 C B^2 (C channels; the
#: multiples of C B^2 below), a speckle filter over windows of at least 100 px within 2
#: disparities (:data:`SPECKLE_SHARE`), and a left-right check within 1 disparity
#: (:data:`LR_MAX_DIFF`: OpenCV's own check, ``disp12MaxDiff``, changes no pixel in this
#: build; ours is :func:`.sgm.drop_left_right`); the uniqueness margin and the switches of the
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
STEP_PENALTY = 8
JUMP_PENALTY = 32
#: Aggregation over the whole cost volume (OpenCV's MODE_HH4: four full paths, along the
#: lines both ways and across them both ways) keeps the volume, about 3.3 bytes a cell
#: (measured): a run takes up to this many cells (0.8 GB), a larger volume runs in strips of
#: rows. OpenCV's 8-path mode (MODE_HH) adds the diagonals, and near the top and bottom
#: of the line images they outvote the paths along the lines: a slanted floor in the
#: last 16 rows of Midd1 took the depth of the surface above it, none of it within 1 px.
#: Over the 60 real cases the four paths gave +0.006 precision and +0.010 coverage at
#: 1 px against the eight (the generated scenes: -0.003 / +0.001), in half the time.
MAX_FULL_VOLUME = 250_000_000
#: A larger volume runs the four paths over strips of rows (:func:`_striped`), each of at
#: most that many cells with this many rows more above and below whose estimates are left
#: out: the paths across the lines run that far into the strip before its first kept row.
#: Against one run over the whole of two generated pairs' line images (cut in two or four
#: strips), 0.05-1.3 % of the cells came more than a column apart with 32 rows, 0.25-1.0 %
#: with 64, 0.16-1.5 % with 16; the margins cost time (in strips of 250 M cells the bench
#: pair took 6 strips with 32 rows and 7 with 64, 28 % longer). The bench pair's peak memory
#: with strips of 250 M cells: 1,535 MB (150 M: 1,205 MB, and its SGM 20-40 % slower).
STRIP_MARGIN = 32


def num_disparities(span: float) -> int:
    """OpenCV's ``numDisparities`` for a search over ``span`` columns: rounded up to a multiple of 16."""
    return int(math.ceil(span / 16.0)) * 16


def speckle_window(rows: int, columns: int, num_d: int, share: float | None = None) -> int:
    """The speckle filter's window (cells) for SGM over line images of ``rows`` x ``columns``
    cells searching ``num_d`` columns: ``share`` (default :data:`SPECKLE_SHARE`) of the cells
    it estimates (OpenCV leaves the first ``num_d`` columns without), at least
    :data:`SPECKLE_WINDOW`."""
    share = SPECKLE_SHARE if share is None else share
    return max(SPECKLE_WINDOW, int(share * rows * max(columns - num_d, 0)))


def speckle_share_for(opt) -> float:
    """The speckle window's share of the view for ``opt`` (``cfg.sgm``): none where
    ``speckle_share`` is off (OpenCV's :data:`SPECKLE_WINDOW` alone)."""
    return SPECKLE_SHARE if opt.speckle_share else 0.0


def sgbm_disparity(L1: np.ndarray, L2: np.ndarray, min_d: int, num_d: int, uniqueness: int, *,
                   full_paths: bool = True, speckle: bool = True, jump: int = JUMP_PENALTY,
                   speckle_share: float | None = None) -> tuple[np.ndarray, bool]:
    """OpenCV's StereoSGBM (the settings above) over line images whose image 2 is shifted by
    ``min_d``, searching ``num_d`` columns: the disparity map (float32 columns, invalid below
    ``min_d``) and whether the four full paths ran. Where their cost volume exceeds
    :data:`MAX_FULL_VOLUME` they run over strips of rows (:func:`_striped`), the speckle
    filter over the whole map after; without ``full_paths``, or where a strip's margins alone
    exceed :data:`MAX_FULL_VOLUME` (:func:`four_paths_fit`), OpenCV's 3 directions."""
    cn = L1.shape[2] if L1.ndim == 3 else 1
    window = speckle_window(*L1.shape[:2], num_d, speckle_share) if speckle else 0
    full = full_paths and four_paths_fit(L1, num_d)
    striped = full and not volume_fits(L1, num_d)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num_d, blockSize=BLOCK,
                                 P1=STEP_PENALTY * cn * BLOCK**2, P2=jump * cn * BLOCK**2,
                                 disp12MaxDiff=LR_MAX_DIFF, uniquenessRatio=uniqueness,
                                 speckleWindowSize=0 if striped else window, speckleRange=SPECKLE_RANGE,
                                 mode=cv2.STEREO_SGBM_MODE_HH4 if full else cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    if striped:
        # fixed point, 4 fractional bits; invalid: -16 (OpenCV's (minDisparity - 1) * 16)
        fixed = _striped(sgbm, L1, L2, strip_rows(L1.shape[1], num_d))
        if window:  # (OpenCV's own filter, as compute runs it, over the whole map)
            cv2.filterSpeckles(fixed, -16, window, SPECKLE_RANGE * 16)
    else:
        fixed = sgbm.compute(L1, L2)
    disp = fixed.astype(np.float32)  # (one float copy)
    disp *= 1.0 / 16.0
    disp += min_d
    return disp, full


def strip_rows(columns: int, num_d: int) -> int:
    """The rows each strip of a striped run keeps (:func:`_striped`) for line images
    ``columns`` wide searching ``num_d`` columns: those whose volume, with
    :data:`STRIP_MARGIN` rows above and below, fits :data:`MAX_FULL_VOLUME`; 0 where not
    even the margins fit."""
    return max(MAX_FULL_VOLUME // max(columns * num_d, 1) - 2 * STRIP_MARGIN, 0)


def _striped(sgbm, L1: np.ndarray, L2: np.ndarray, core: int) -> np.ndarray:
    """``sgbm``'s (int16, fixed point) disparity of ``L1`` against ``L2`` over strips of
    ``core`` rows, one after the other (OpenCV's four paths use every core). Each strip runs
    with :data:`STRIP_MARGIN` rows more above and below (where the image has them), whose
    estimates are left out: there the paths across the lines start, as they do at the
    image's first and last rows."""
    rows = L1.shape[0]
    out = np.empty(L1.shape[:2], np.int16)
    for top in range(0, rows, core):
        lo, hi = max(top - STRIP_MARGIN, 0), min(top + core + STRIP_MARGIN, rows)
        end = min(top + core, rows)
        out[top:end] = sgbm.compute(L1[lo:hi], L2[lo:hi])[top - lo:end - lo]
    return out


def four_paths_fit(L1: np.ndarray, num_d: int) -> bool:
    """Whether OpenCV's four full paths can run over line images shaped as ``L1`` searching
    ``num_d`` columns: in one run or in strips (:func:`strip_rows`); else its 3 directions."""
    return volume_fits(L1, num_d) or strip_rows(L1.shape[1], num_d) > 0


def volume_fits(L1: np.ndarray, num_d: int) -> bool:
    """Whether the cost volume of line images shaped as ``L1`` over ``num_d`` columns fits
    :data:`MAX_FULL_VOLUME` (OpenCV's four full paths in one run; else in strips)."""
    return L1.shape[0] * L1.shape[1] * num_d <= MAX_FULL_VOLUME
