"""Point-cloud post-processing: normals, outlier removal, colour sampling.

Pure functions on numpy arrays. open3d is imported lazily inside the functions
that use it (its import costs ~1 s).
"""

from __future__ import annotations

import logging

import numpy as np
from numba import njit, prange

from ..geometry.epipolar import bilinear

log = logging.getLogger(__name__)

__all__ = ["clean_points", "estimate_normals", "sample_colors"]


def _as_xyz(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be (N, 3), got {xyz.shape}")
    return xyz


def _pcd(xyz: np.ndarray):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, dtype=np.float64))
    return pcd


def estimate_normals(
    xyz: np.ndarray,
    camera_centers: np.ndarray,
    k: int = 16,
    radius: float | None = None,
) -> np.ndarray:
    """Unit normals by local PCA (open3d), oriented towards the first camera.

    Args:
        xyz: (N, 3) float points, world units. N >= 3.
        camera_centers: (M, 3) or (3,) camera centres ``C = -R.T @ t`` (world).
            Only the FIRST centre is used for orientation: each normal is flipped
            so that ``dot(n, C0 - X) >= 0`` (it faces the reference camera, which
            sees every point of a two-view reconstruction).
        k: number of nearest neighbours (KNN search), or the cap on neighbours
            when ``radius`` is given.
        radius: if given, hybrid search: up to ``k`` neighbours within
            ``radius`` (world units). Points with < 3 neighbours in the radius
            get an arbitrary (but still camera-facing) normal from open3d.

    Returns:
        (N, 3) float64 unit normals. Non-finite input points get NaN normals
        (they are excluded from the neighbour search).
    """
    import open3d as o3d

    xyz = _as_xyz(xyz)
    centers = np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3)
    if len(centers) == 0:
        raise ValueError("need at least one camera centre to orient normals")
    if k < 3:
        raise ValueError(f"k must be >= 3, got {k}")
    finite = np.isfinite(xyz).all(axis=1)
    normals = np.full_like(xyz, np.nan)
    pts = xyz[finite]
    if len(pts) < 3:
        raise ValueError(f"need at least 3 finite points for normals, got {len(pts)}")
    pcd = _pcd(pts)
    if radius is None:
        param = o3d.geometry.KDTreeSearchParamKNN(knn=int(k))
    else:
        param = o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius), max_nn=int(k))
    pcd.estimate_normals(search_param=param, fast_normal_computation=False)
    n = np.asarray(pcd.normals, dtype=np.float64).copy()
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    flip = np.einsum("ij,ij->i", n, centers[0] - pts) < 0
    n[flip] *= -1.0
    normals[finite] = n
    return normals


def clean_points(
    xyz: np.ndarray,
    nb_neighbors: int = 16,
    std_ratio: float = 2.5,
) -> np.ndarray:
    """Statistical outlier removal (open3d); returns a keep mask.

    A point is kept when its mean distance to its ``nb_neighbors`` nearest
    neighbours is below ``mean + std_ratio * std`` of that statistic over the
    cloud. Non-finite points are always dropped. Clouds with at most
    ``nb_neighbors`` finite points are returned unfiltered (all finite kept).

    Args:
        xyz: (N, 3) float points.

    Returns:
        (N,) bool mask, True = keep. Filter colours etc. with it.
    """
    xyz = _as_xyz(xyz)
    keep = np.isfinite(xyz).all(axis=1)
    idx = np.flatnonzero(keep)
    if len(idx) <= nb_neighbors:
        return keep
    _, inliers = _pcd(xyz[idx]).remove_statistical_outlier(
        nb_neighbors=int(nb_neighbors), std_ratio=float(std_ratio)
    )
    mask = np.zeros(len(xyz), dtype=bool)
    mask[idx[np.asarray(inliers, dtype=np.int64)]] = True
    log.debug("clean_points: kept %d of %d", int(mask.sum()), len(xyz))
    return mask


def bilinear_corners(h: int, w: int, uv: np.ndarray):
    """Rows i0, i1, columns j0, j1 and weights fx, fy of the 2x2 pixel centres around ``uv``.

    ``uv`` (N, 2) are COLMAP positions (pixel (row i, col j) has its centre at
    (j + 0.5, i + 0.5)), clamped to an (h, w) image.
    """
    x = np.clip(uv[:, 0] - 0.5, 0.0, w - 1.0)
    y = np.clip(uv[:, 1] - 0.5, 0.0, h - 1.0)
    j0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    i0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    return i0, np.minimum(i0 + 1, h - 1), j0, np.minimum(j0 + 1, w - 1), x - j0, y - i0


def sample_colors(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colour lookup at COLMAP pixel coordinates.

    Args:
        image: (H, W, 3) uint8 (or (H, W) grey, or float) image.
        uv: (N, 2) float pixel coordinates, COLMAP convention (centre of the
            top-left pixel is (0.5, 0.5)). Positions outside the image are
            clamped to the border pixels; non-finite uv give 0.

    Returns:
        (N, 3) uint8 (or (N,) for a 2-D image), rounded to nearest.
    """
    img = np.asarray(image)
    if img.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got {img.shape}")
    uv = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 2)
    out = _bilinear_sample(img if img.ndim == 3 else img[:, :, None], uv)
    out[np.isnan(out)] = 0  # non-finite positions
    if img.ndim == 2:
        out = out[:, 0]
    if np.issubdtype(img.dtype, np.integer):
        # a weighted mean of the image's own values: within its type's range, no clipping needed
        return np.rint(out, out=out).astype(img.dtype)
    return out.astype(img.dtype)


def grid_normals(uv: np.ndarray, xyz: np.ndarray, shape: tuple[int, int], step: int = 2) -> np.ndarray:
    """Normals from the image grid: cross product of the 3-D differences to the grid neighbours.

    Dense matches sit on camera 1's pixel grid, so the neighbours that a KD-tree
    would search for are the points of the neighbouring pixels. Each point's
    normal is ``(X[r, c+s] - X[r, c-s]) x (X[r+s, c] - X[r-s, c])``, one-sided
    where a neighbour is missing, oriented towards camera 1 (at the origin).
    Points without neighbours in both directions face the camera. Linear time,
    unlike a KD-tree search over millions of points.

    Args:
        uv: (N, 2) positions in camera 1's image (COLMAP pixels). xyz: (N, 3) in camera 1's frame.
        shape: (height, width) of that image. step: neighbour distance, pixels.
    Returns:
        (N, 3) unit normals.
    """
    xyz = np.ascontiguousarray(_as_xyz(xyz))
    h, w = int(shape[0]), int(shape[1])
    r = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 1)
    c = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 1)
    return _grid_normals(xyz, r, c, h, w, int(step))


# ------------------------------------------------------------------ numba kernels


@njit(cache=True)
def _neighbour(index, r, c, h, w):
    if r < 0 or r >= h or c < 0 or c >= w:
        return -1
    return index[r, c]


@njit(cache=True)
def _difference(xyz, index, k, r, c, dr, dc, h, w):
    """``X`` of the point ``(dr, dc)`` pixels beyond point ``k`` (at ``r``, ``c``) less that of the
    point as far before it; the point itself stands in for a missing neighbour."""
    kf = _neighbour(index, r + dr, c + dc, h, w)
    kb = _neighbour(index, r - dr, c - dc, h, w)
    if kf < 0:
        kf = k
    if kb < 0:
        kb = k
    return xyz[kf, 0] - xyz[kb, 0], xyz[kf, 1] - xyz[kb, 1], xyz[kf, 2] - xyz[kb, 2]


@njit(parallel=True, cache=True)
def _grid_normals(xyz, r, c, h, w, step):
    """Unit normals (N, 3) from the grid neighbours' 3-D differences; see :func:`grid_normals`."""
    n = xyz.shape[0]
    index = np.full((h, w), -1, np.int64)
    for k in range(n):
        index[r[k], c[k]] = k  # one point per pixel (the last wins)
    out = np.empty((n, 3))
    for kk in prange(n):
        k = np.int64(kk)  # prange's index may be unsigned; keep index arithmetic in int64
        ax, ay, az = _difference(xyz, index, k, r[k], c[k], 0, step, h, w)  # along x (columns)
        bx, by, bz = _difference(xyz, index, k, r[k], c[k], step, 0, h, w)  # along y (rows)
        nx = ay * bz - az * by
        ny = az * bx - ax * bz
        nz = ax * by - ay * bx
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        pn = np.sqrt(xyz[k, 0] ** 2 + xyz[k, 1] ** 2 + xyz[k, 2] ** 2) + 1e-12
        vx = -xyz[k, 0] / pn
        vy = -xyz[k, 1] / pn
        vz = -xyz[k, 2] / pn
        if norm > 0.0:
            nx /= norm
            ny /= norm
            nz /= norm
            if nx * vx + ny * vy + nz * vz < 0.0:
                nx = -nx
                ny = -ny
                nz = -nz
        else:
            nx = vx
            ny = vy
            nz = vz
        out[k, 0] = nx
        out[k, 1] = ny
        out[k, 2] = nz
    return out


@njit(parallel=True, cache=True)
def _bilinear_sample(img, uv):
    """Bilinear samples (N, C) float32 of ``img`` (H, W, C) at COLMAP positions ``uv`` (N, 2).

    Border replicated (:func:`sefm_recon.geometry.epipolar.bilinear`, the line
    sampler's; the same values as :func:`bilinear_corners`
    gives); NaN where ``uv`` is not finite.
    """
    C = img.shape[2]
    n = uv.shape[0]
    out = np.empty((n, C), np.float32)
    for kk in prange(n):
        k = np.int64(kk)
        if np.isfinite(uv[k, 0]) and np.isfinite(uv[k, 1]):
            for ch in range(C):
                out[k, ch] = bilinear(img, uv[k, 0], uv[k, 1], ch)
        else:
            for ch in range(C):
                out[k, ch] = np.nan
    return out
