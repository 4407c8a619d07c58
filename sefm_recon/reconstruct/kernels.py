"""numba kernels of the reconstruction stage (points on camera 1's pixel grid)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..geometry.kernels import bilinear


@njit(cache=True)
def _neighbour(index, r, c, h, w):
    if r < 0 or r >= h or c < 0 or c >= w:
        return -1
    return index[r, c]


@njit(parallel=True, cache=True)
def grid_normals(xyz, r, c, h, w, step):
    """Unit normals (N, 3) from the grid neighbours' 3-D differences; see points.grid_normals."""
    n = xyz.shape[0]
    index = np.full((h, w), -1, np.int64)
    for k in range(n):
        index[r[k], c[k]] = k  # one point per pixel (the last wins)
    out = np.empty((n, 3))
    for kk in prange(n):
        k = np.int64(kk)  # prange's index may be unsigned; keep index arithmetic in int64
        # along x (columns)
        kf = _neighbour(index, r[k], c[k] + step, h, w)
        kb = _neighbour(index, r[k], c[k] - step, h, w)
        if kf < 0:
            kf = k
        if kb < 0:
            kb = k
        ax = xyz[kf, 0] - xyz[kb, 0]
        ay = xyz[kf, 1] - xyz[kb, 1]
        az = xyz[kf, 2] - xyz[kb, 2]
        # along y (rows)
        kf = _neighbour(index, r[k] + step, c[k], h, w)
        kb = _neighbour(index, r[k] - step, c[k], h, w)
        if kf < 0:
            kf = k
        if kb < 0:
            kb = k
        bx = xyz[kf, 0] - xyz[kb, 0]
        by = xyz[kf, 1] - xyz[kb, 1]
        bz = xyz[kf, 2] - xyz[kb, 2]
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
def bilinear_sample(img, uv):
    """Bilinear samples (N, C) float32 of ``img`` (H, W, C) at COLMAP positions ``uv`` (N, 2).

    Border replicated (:func:`sefm_recon.geometry.kernels.bilinear`, the line
    sampler's; the same values as :func:`sefm_recon.reconstruct.points.bilinear_corners`
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
