"""Inconsistency handling (paper §4.5).

S_v, the segment validity, is applied inside the line kernel
(:func:`sefm_recon.matching.kernels.match_one_line`), where the key points are at
hand. S_p, the pixel validity from depth jumps, needs triangulated depths and is
here.
"""

from __future__ import annotations

import numpy as np

from . import kernels


def depth_continuity(depth: np.ndarray, line: np.ndarray, jump: float = 0.05, min_run: int = 5,
                     mask: np.ndarray | None = None) -> np.ndarray:
    """S_p: keep mask of points whose depth continues along their epipolar line.

    Args:
        depth: (N,) depth of each match (any positive unit), in line order.
        line: (N,) line index of each match, non-decreasing.
        jump: relative depth change between consecutive points that counts as a jump.
        min_run: runs between jumps shorter than this are dropped as spikes.
        mask: (N,) points that take part (default all); the others are skipped and not kept.
    """
    depth = np.ascontiguousarray(depth, np.float64)
    line = np.ascontiguousarray(line, np.int64)
    if len(depth) == 0:
        return np.zeros(0, bool)
    mask = np.ones(len(depth), bool) if mask is None else np.ascontiguousarray(mask, bool)
    return kernels.depth_runs_filter(depth, line, float(jump), int(min_run), mask)


def neighbour_consistency(uv: np.ndarray, inv_depth: np.ndarray, shape: tuple[int, int], radius: int = 2,
                          tol: float = 1e-3, min_support: int = 6, drop_isolated: bool = False,
                          mask: np.ndarray | None = None) -> np.ndarray:
    """2-D consistency across neighbouring line pairs: keep mask (N,).

    Scanline DP decides each line alone, which leaves streaks: runs of wrong
    matches that disagree with the lines beside them. Each match's inverse
    depth (proportional to disparity) is compared with the median of the other
    matches in its ``(2 radius + 1)^2`` pixel window of image 1; matches farther
    than ``tol`` from it are dropped (``tol`` in inverse-depth units: a pixel
    of disparity is about ``1 / (f * baseline)``). Matches with fewer than
    ``min_support`` neighbours are kept, or dropped with ``drop_isolated``
    (an isolated match in a dense field is most often a wrong one).

    Args:
        uv: (N, 2) positions in image 1 (COLMAP pixels). shape: (height, width).
        mask: (N,) matches that take part (default all); the others are not kept.
    """
    # The same pass without the median estimate (bins = 0).
    return neighbour_median(uv, inv_depth, shape, radius, tol, min_support, drop_isolated, mask, bins=0)[0]


def neighbour_median(uv: np.ndarray, inv_depth: np.ndarray, shape: tuple[int, int], radius: int = 2,
                     tol: float = 1e-3, min_support: int = 6, drop_isolated: bool = False,
                     mask: np.ndarray | None = None, bins: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """:func:`neighbour_consistency`, and the neighbours' median: ``keep`` (N,), ``median`` (N,).

    The median is also the better inverse depth of a kept match: each line's
    DP and sub-pixel step place a partner from that line's samples alone, so
    on a surface the partners scatter by a fraction of a pixel around the
    truth, most where an edge runs along the line (the line then says little
    about where along it the partner lies). Being a median, it keeps straight
    depth edges. It is estimated to within ``2 tol / bins`` (one bin of a
    histogram of the neighbours within ``tol``; exact ranks cost four times
    the check). Dropped matches, those with fewer than ``min_support``
    neighbours and those without ``mask`` get their own value; so does every
    match with ``bins`` = 0 (the check alone).
    """
    inv_depth = np.ascontiguousarray(inv_depth, np.float64)
    if len(uv) == 0:
        return np.zeros(0, bool), np.zeros(0)
    mask = np.ones(len(uv), bool) if mask is None else np.ascontiguousarray(mask, bool)
    keep, _, median = kernels.grid_median_check(np.ascontiguousarray(uv, np.float64), inv_depth, mask,
                                                int(shape[0]), int(shape[1]), int(radius), float(tol),
                                                int(min_support), bool(drop_isolated), int(bins))
    return keep, median
