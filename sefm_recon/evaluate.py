"""Match accuracy against ground-truth depth (synthetic scenes).

Definitions (COLMAP pixel convention, see ``docs/CONVENTIONS.md``):

* The **true correspondence** of a position ``uv1`` in view 1 is found by taking the
  depth of view 1 at ``uv1`` (bilinear interpolation between the four surrounding
  pixel centres, or the depth of the pixel containing ``uv1`` where those four span a
  depth discontinuity: relative spread > ``DISCONTINUITY_REL`` or an ``inf``),
  back-projecting along the exact ray of ``uv1`` and projecting into view 2.
* It is **co-visible** iff the depth is finite, the point lies in front of camera 2,
  projects inside image 2 (``0 <= u < W``, ``0 <= v < H``) and is not occluded in
  view 2: its camera-2 z must not exceed ``(1 + OCCLUSION_REL)`` times the *largest*
  depth of the (up to) four pixel centres of view 2 surrounding ``uv2``.  Taking the
  largest of the four (rather than only the nearest pixel) keeps surfaces seen at
  grazing angles visible, where depth changes by several percent from one pixel to
  the next; the price is that points within one pixel of an occluding edge in view 2
  count as visible.
* ``precision@t`` = (#matches that are co-visible and within ``t`` px, Euclidean, of
  the true correspondence) / (#matches).
* ``coverage@t`` = (#co-visible pixels of image 1, evaluated at pixel centres, that
  hold at least one correct match at ``t``; a match is held by pixel
  ``floor(uv1)``) / (#co-visible pixels of image 1).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "DISCONTINUITY_REL",
    "OCCLUSION_REL",
    "sample_depth",
    "true_correspondences",
    "covisibility_mask",
    "evaluate_matches",
    "score_matches",
    "pixel_index",
    "surface_distances",
]

DISCONTINUITY_REL = 0.01  # relative depth spread of a 2x2 neighbourhood that counts as an edge
OCCLUSION_REL = 0.01  # relative depth tolerance of the occlusion test


def _corners(depth: np.ndarray, uv: np.ndarray):
    """Indices and weights of the 2x2 pixel centres around COLMAP positions ``uv``."""
    from .reconstruct.points import bilinear_corners

    return bilinear_corners(depth.shape[0], depth.shape[1], uv)


def pixel_index(uv: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Row and column (each (N,) int64) of the pixels holding COLMAP positions ``uv`` (N, 2),
    clamped to an image of ``shape`` (H, W, ...)."""
    i = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, shape[0] - 1)
    j = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, shape[1] - 1)
    return i, j


def _nearest(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth of the pixel containing ``uv`` (clamped to the image)."""
    return depth[pixel_index(uv, depth.shape)].astype(np.float64)


def sample_depth(depth: np.ndarray, uv: np.ndarray, rel: float = DISCONTINUITY_REL) -> np.ndarray:
    """Depth at fractional COLMAP positions: bilinear, nearest pixel across discontinuities."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros(0)
    i0, i1, j0, j1, fx, fy = _corners(depth, uv)
    d00 = depth[i0, j0].astype(np.float64)
    d01 = depth[i0, j1].astype(np.float64)
    d10 = depth[i1, j0].astype(np.float64)
    d11 = depth[i1, j1].astype(np.float64)
    dmin = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
    dmax = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
    with np.errstate(invalid="ignore"):
        smooth = np.isfinite(dmax) & (dmin > 0) & (dmax - dmin <= rel * dmin)
        bil = (d00 * (1 - fx) + d01 * fx) * (1 - fy) + (d10 * (1 - fx) + d11 * fx) * fy
    return np.where(smooth, bil, _nearest(depth, uv))


def _project(view1, view2, uv1: np.ndarray, d1: np.ndarray):
    """Back-project ``uv1`` at z-depth ``d1`` from view 1; return (uv2, z2)."""
    K1 = np.asarray(view1.K, np.float64)
    R1 = np.asarray(view1.R, np.float64)
    t1 = np.asarray(view1.t, np.float64).reshape(3)
    K2 = np.asarray(view2.K, np.float64)
    R2 = np.asarray(view2.R, np.float64)
    t2 = np.asarray(view2.t, np.float64).reshape(3)
    rays = np.column_stack([uv1, np.ones(len(uv1))]) @ np.linalg.inv(K1).T  # z = 1
    with np.errstate(invalid="ignore"):
        Xc1 = rays * d1[:, None]
        # X2 = R2 R1^T (X1 - t1) + t2
        R21 = R2 @ R1.T
        Xc2 = Xc1 @ R21.T + (t2 - R21 @ t1)
        p = Xc2 @ K2.T
        z2 = Xc2[:, 2]
        with np.errstate(divide="ignore"):
            uv2 = p[:, :2] / p[:, 2:3]
    return uv2, z2


def true_correspondences(view1, view2, uv1) -> tuple[np.ndarray, np.ndarray]:
    """True positions in view 2 of COLMAP positions ``uv1`` (N, 2) of view 1.

    Returns ``(uv2_true (N, 2) float64, covisible (N,) bool)``; ``uv2_true`` is NaN
    where the depth of view 1 is not finite or ``uv1`` lies outside image 1 (or is
    not finite); such positions are not co-visible.
    """
    uv1 = np.asarray(uv1, np.float64).reshape(-1, 2)
    n = len(uv1)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    H1, W1 = view1.depth.shape
    with np.errstate(invalid="ignore"):
        in1 = (uv1[:, 0] >= 0) & (uv1[:, 0] < W1) & (uv1[:, 1] >= 0) & (uv1[:, 1] < H1)
    d1 = sample_depth(view1.depth, np.where(in1[:, None], uv1, 0.5))
    fin = in1 & np.isfinite(d1) & (d1 > 0)
    d1 = np.where(fin, d1, np.nan)
    uv2, z2 = _project(view1, view2, uv1, d1)
    H2, W2 = view2.depth.shape
    with np.errstate(invalid="ignore"):
        ok = fin & (z2 > 0) & np.isfinite(uv2).all(axis=1)
        ok &= (uv2[:, 0] >= 0) & (uv2[:, 0] < W2) & (uv2[:, 1] >= 0) & (uv2[:, 1] < H2)
    cov = np.zeros(n, bool)
    idx = np.nonzero(ok)[0]
    if idx.size:
        D2 = view2.depth
        i0, i1, j0, j1, _, _ = _corners(D2, uv2[idx])
        dref = np.maximum(np.maximum(D2[i0, j0], D2[i0, j1]), np.maximum(D2[i1, j0], D2[i1, j1])).astype(np.float64)
        cov[idx] = z2[idx] <= dref * (1.0 + OCCLUSION_REL)
    return uv2, cov


def covisibility_mask(view1, view2) -> np.ndarray:
    """(H, W) bool: pixels of view 1 whose centre is co-visible in view 2."""
    H, W = view1.depth.shape
    ii, jj = np.mgrid[0:H, 0:W]
    uv = np.column_stack([jj.ravel() + 0.5, ii.ravel() + 0.5])
    return true_correspondences(view1, view2, uv)[1].reshape(H, W)


def evaluate_matches(uv1, uv2, view1, view2, thresholds=(1.0, 3.0), covisible=None) -> dict:
    """Precision / coverage of matches ``uv1 <-> uv2`` (COLMAP coords) at ``thresholds`` px.

    ``covisible``: optional precomputed :func:`covisibility_mask` (view1, view2).
    """
    cov_mask = covisibility_mask(view1, view2) if covisible is None else covisible
    return score_matches(uv1, uv2, lambda uv: true_correspondences(view1, view2, uv), cov_mask, thresholds)


def score_matches(uv1, uv2, truth, covisible, thresholds=(1.0, 3.0)) -> dict:
    """Precision / coverage of matches against any ground truth (the definitions above).

    ``truth(uv1 (N, 2)) -> (uv2_true (N, 2), covisible (N,) bool)`` gives the true
    correspondence of COLMAP positions of image 1 (:func:`true_correspondences` for a
    rendered scene, :meth:`sefm_recon.realgt.StereoCase.truth` for a real pair);
    ``covisible`` is the (H, W) bool mask of image 1's co-visible pixel centres.
    """
    uv1 = np.asarray(uv1, np.float64).reshape(-1, 2)
    uv2 = np.asarray(uv2, np.float64).reshape(-1, 2)
    if len(uv1) != len(uv2):
        raise ValueError(f"uv1 and uv2 differ in length: {len(uv1)} vs {len(uv2)}")
    n = len(uv1)
    cov_mask = np.asarray(covisible, bool)
    H, W = cov_mask.shape
    n_cov = int(cov_mask.sum())
    uv2_true, cov = truth(uv1) if n else (np.zeros((0, 2)), np.zeros(0, bool))
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(uv2 - uv2_true, axis=1) if n else np.zeros(0)
    with np.errstate(invalid="ignore"):
        inside = (uv1[:, 0] >= 0) & (uv1[:, 0] < W) & (uv1[:, 1] >= 0) & (uv1[:, 1] < H)
    uvi = np.where(inside[:, None], uv1, 0.0)
    j = np.floor(uvi[:, 0]).astype(np.int64)
    i = np.floor(uvi[:, 1]).astype(np.int64)
    prec: dict = {}
    covg: dict = {}
    for thr in thresholds:
        key = f"{float(thr):g}"
        with np.errstate(invalid="ignore"):
            good = cov & (err <= thr)
        prec[f"precision@{key}"] = float(good.sum() / n) if n else 0.0
        held = np.zeros((H, W), bool)
        g = good & inside
        held[i[g], j[g]] = True
        covg[f"coverage@{key}"] = float((held & cov_mask).sum() / n_cov) if n_cov else 0.0
    return {"matches": n, **prec, **covg, "covisible_pixels": n_cov}


def surface_distances(xyz, views) -> np.ndarray:
    """Upper bound of each world point's distance to the true surface, (N,).

    For every view the point projects into (in front of the camera, inside the
    image, finite depth there), the surface point on the same viewing ray is the
    one at the view's depth ``d`` (:func:`sample_depth`); the point lies
    ``|z - d| * |K^-1 (u, v, 1)|`` from it. The smallest such distance over the
    views bounds the distance to the surface from above. ``inf`` where no view
    has a depth for the point. ``views`` need ``K, R, t, depth`` (world -> camera,
    COLMAP conventions).
    """
    X = np.asarray(xyz, np.float64).reshape(-1, 3)
    best = np.full(len(X), np.inf)
    for v in views:
        K = np.asarray(v.K, np.float64)
        R = np.asarray(v.R, np.float64)
        t = np.asarray(v.t, np.float64).reshape(3)
        H, W = v.depth.shape
        Xc = X @ R.T + t
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            p = Xc @ K.T
            uv = p[:, :2] / p[:, 2:3]
            ok = (z > 0) & np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            continue
        d = sample_depth(v.depth, uv[idx])
        ray = np.column_stack([uv[idx], np.ones(idx.size)]) @ np.linalg.inv(K).T
        with np.errstate(invalid="ignore"):
            e = np.abs(z[idx] - d) * np.linalg.norm(ray, axis=1)
        e = np.where(np.isfinite(e), e, np.inf)
        best[idx] = np.minimum(best[idx], e)
    return best
