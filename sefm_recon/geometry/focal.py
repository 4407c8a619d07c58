"""The focal length from the pair itself, when neither ``--camera`` nor EXIF gives it.

The fundamental matrix ``F`` of a pair holds the focal length where the geometry
allows: with the right cameras ``E = K2^T F K1`` is an essential matrix, whose two
non-zero singular values are equal (Mendonca and Cipolla, CVPR 1999; the cost COLMAP's
view-graph calibration minimises). With the principal point at the image centre
and one field of view for both photos (:func:`focal_matrix`), that leaves one
unknown, found by a 1-D search (:func:`estimate_focal`).

Where the optical axes are parallel (a rectified pair) or meet at a point as far
from both cameras (both turned towards it alike), ``F`` does not fix the shared focal
length: every value makes an essential matrix (Newsam et al. 1996; :attr:`FocalEstimate.determined`
is then False). The epipolar lines are the same whatever the focal length, so the
matches are right and only the depths' scale along the viewing rays is not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

#: Fields of view searched (deg across the longer side), those :mod:`sefm_recon.io.cameras`
#: accepts from a user: a focal length outside them is refused there too.
SEARCH_FOV_DEG = (1.0, 170.0)
#: Steps of the coarse search per factor of 2 in focal length: 60 steps make 1.2 % a
#: step, below the few per cent to which the noise of real SIFT matches fixes it.
STEPS_PER_OCTAVE = 60
#: The focal length counts as determined by the pair when a focal length 1.5 times
#: too long or too short raises the cost (the relative gap between E's two singular
#: values) by this much: on fountain-P11's neighbours the noise of F leaves 3e-5 to
#: 2.5e-3 at the minimum and a 1.5x error raises it by 0.006-0.033; a rectified pair
#: raises it by nothing.
MIN_COST_RISE = 5e-3
#: ... and by this many times the cost left at the minimum, the noise of ``F`` itself:
#: a generated pair whose cameras look at one point kept 0.009 there and rose by less
#: (its estimate was 29 % off), fountain-P11's neighbours rise by 2.8 to 40 times.
MIN_RISE_OVER_COST = 2.0
#: ... the factor of that test: the default guess (1.2 x the longer side) is within it
#: of most cameras (a 28-60 mm equivalent lens), so an undetermined estimate is no worse.
DETERMINED_FACTOR = 1.5


@dataclass
class FocalEstimate:
    """The shared focal factor ``f / max(W, H)`` estimated from a fundamental matrix."""

    factor: float  #: focal length over the longer image side
    cost: float  #: the cost at ``factor`` (0 for an exact essential matrix)
    rise: float  #: the least rise of the cost at ``factor`` times and over :data:`DETERMINED_FACTOR`
    num_inliers: int  #: inliers of the fundamental matrix

    @property
    def determined(self) -> bool:
        return bool(self.rise >= max(MIN_COST_RISE, MIN_RISE_OVER_COST * self.cost))


def focal_matrix(factor: float, size: tuple[int, int]) -> np.ndarray:
    """``K`` (3, 3) with ``f = factor * max(W, H)`` and the principal point at the centre (COLMAP pixels)."""
    w, h = size
    return np.array([[factor * max(w, h), 0.0, w / 2.0], [0.0, factor * max(w, h), h / 2.0], [0.0, 0.0, 1.0]])


def essential_cost(F: np.ndarray, K1: np.ndarray, K2: np.ndarray) -> float:
    """Relative gap ``(s1 - s2) / s1`` between the two largest singular values of ``K2^T F K1``."""
    s = np.linalg.svd(K2.T @ F @ K1, compute_uv=False)
    return float((s[0] - s[1]) / max(s[0], 1e-300))


def fundamental_matrix(xy1: np.ndarray, xy2: np.ndarray, max_error: float = 2.0) -> tuple[np.ndarray, np.ndarray] | None:
    """``F`` (3, 3) by COLMAP's LO-RANSAC, and its inlier mask (M,), or None when it fails."""
    if len(xy1) < 8:
        return None
    opts = pycolmap.RANSACOptions()
    opts.max_error = float(max_error)
    opts.random_seed = 0
    r = pycolmap.estimate_fundamental_matrix(np.ascontiguousarray(xy1, np.float64),
                                             np.ascontiguousarray(xy2, np.float64), opts)
    if r is None:
        return None
    return np.asarray(r["F"], np.float64), np.asarray(r["inlier_mask"], bool).ravel()


def estimate_focal(F: np.ndarray, size1: tuple[int, int], size2: tuple[int, int], *, K1: np.ndarray | None = None,
                   K2: np.ndarray | None = None, num_inliers: int = 0) -> FocalEstimate:
    """The focal factor that makes ``F`` most nearly essential: a log-spaced search, then a parabola.

    Args:
        F: (3, 3) fundamental matrix, COLMAP pixel coordinates of the two images.
        size1, size2: (width, height) of the images ``F`` relates.
        K1, K2: a camera that is known (given or from EXIF) stays as it is; the
            unknown ones share the factor searched for.
    """
    lo, hi = (0.5 / np.tan(np.radians(fov) / 2) for fov in SEARCH_FOV_DEG[::-1])
    n = int(np.ceil(np.log2(hi / lo) * STEPS_PER_OCTAVE)) + 1
    grid = np.exp(np.linspace(np.log(lo), np.log(hi), n))

    def cost(factor: float) -> float:
        return essential_cost(F, focal_matrix(factor, size1) if K1 is None else K1,
                              focal_matrix(factor, size2) if K2 is None else K2)

    costs = np.array([cost(g) for g in grid])
    k = int(np.argmin(costs))
    best = grid[k]
    if 0 < k < n - 1:  # the parabola's vertex through the three grid points, in log focal length
        c0, c1, c2 = costs[k - 1], costs[k], costs[k + 1]
        den = c0 - 2 * c1 + c2
        if den > 0:
            step = np.log(grid[1] / grid[0])
            best = float(np.exp(np.log(best) + 0.5 * step * (c0 - c2) / den))
    c = cost(best)
    rise = min(cost(best * DETERMINED_FACTOR), cost(best / DETERMINED_FACTOR)) - c
    return FocalEstimate(float(best), c, float(rise), int(num_inliers))
