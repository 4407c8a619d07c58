"""Inconsistency handling (paper §4.5).

S_v, the segment validity, is applied inside the line kernel
(:func:`sefm_recon.matching.kernels.match_one_line`), where the key points are at
hand. S_p, the pixel validity from depth jumps, needs triangulated depths and is
here.
"""

from __future__ import annotations

import numpy as np

from . import kernels


def depth_continuity(depth: np.ndarray, line: np.ndarray, jump: float = 0.05, min_run: int = 5) -> np.ndarray:
    """S_p: keep mask of points whose depth continues along their epipolar line.

    Args:
        depth: (N,) depth of each match (any positive unit), in line order.
        line: (N,) line index of each match, non-decreasing.
        jump: relative depth change between consecutive points that counts as a jump.
        min_run: runs between jumps shorter than this are dropped as spikes.
    """
    depth = np.ascontiguousarray(depth, np.float64)
    line = np.ascontiguousarray(line, np.int64)
    if len(depth) == 0:
        return np.zeros(0, bool)
    if np.any(np.diff(line) < 0):
        raise ValueError("points must be sorted by line")
    return kernels.depth_runs_filter(depth, line, float(jump), int(min_run))
