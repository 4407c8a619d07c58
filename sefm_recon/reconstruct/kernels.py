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


# ------------------------------------------------------------------ multi-view fusion (see fuse.py)


@njit(cache=True)
def zbuffer_insert(depth, nmap, pix, z, nq):
    """Keep the nearest depth (and its quantised normal) of each pixel; ``pix`` -1 = not in the view."""
    for k in range(pix.shape[0]):
        p = pix[k]
        if p >= 0 and z[k] < depth[p]:
            depth[p] = z[k]
            nmap[p, 0] = nq[k, 0]
            nmap[p, 1] = nq[k, 1]
            nmap[p, 2] = nq[k, 2]


@njit(cache=True)
def _window(depth, nmap, off, w, h, p, z, nq, tol, cos_min, r):
    """Around pixel ``p`` of one view: (an agreeing depth found, nearest depth in the window)."""
    x0 = p % w
    y0 = p // w
    agree = False
    wmin = np.inf
    for dy in range(-r, r + 1):
        y = y0 + dy
        if y < 0 or y >= h:
            continue
        for dx in range(-r, r + 1):
            x = x0 + dx
            if x < 0 or x >= w:
                continue
            q = off + y * w + x
            d = depth[q]
            if d < wmin:
                wmin = d
            if abs(d - z) <= tol * z:
                if cos_min > -1.0:
                    dot = (np.float64(nmap[q, 0]) * nq[0] + np.float64(nmap[q, 1]) * nq[1]
                           + np.float64(nmap[q, 2]) * nq[2]) / (127.0 * 127.0)
                    if dot < cos_min:
                        continue
                agree = True
    return agree, wmin


@njit(cache=True)
def fuse_block(a, b, pix, z, xyz, rgb, nrm, nq, depth, nmap, near, offs, widths, heights, adj,
               owner, fdepth, sxyz, srgb, snrm, nobs, track, n_fused, counts,
               tol, cos_min, r, min_agree):
    """Judge and merge one block of a pair's points against every view's depth map.

    ``pix``/``z`` (V, n): each point's pixel (flat, -1 outside or behind) and depth
    in every view. A point is kept when at least ``max(min_agree, 1)`` other views
    agree and fewer contradict than agree; with ``min_agree`` 0 also when no view
    agrees, contradicts or hides it. A kept point
    joins the fused point that already owns its pixel in one of its views (at a
    consistent depth), else starts one; it then claims its pixels in those views.
    ``counts``: [kept, kept without other views, free-space drops, background
    drops, merged into an existing point, drops hidden in another view, drops
    with too few agreeing views].
    """
    V = pix.shape[0]
    n = pix.shape[1]
    inview = np.zeros(V, np.bool_)
    for k in range(n):
        agree = 0
        contra = 0
        freesp = 0
        hidden = 0
        for j in range(V):
            inview[j] = False
        inview[a] = pix[a, k] >= 0
        inview[b] = pix[b, k] >= 0
        for j in (a, b):  # a nearer surface at the very pixel that observed the point: another pair saw through it
            if inview[j] and depth[offs[j] + pix[j, k]] < z[j, k] * (1.0 - tol):
                contra += 1
                freesp += 1
        for j in range(V):
            p = pix[j, k]
            if j == a or j == b or p < 0:
                continue
            zj = z[j, k]
            ok, wmin = _window(depth, nmap, offs[j], widths[j], heights[j], p, zj, nq[k], tol, cos_min, r)
            if ok:
                agree += 1
                inview[j] = True
            elif wmin < np.inf:
                if wmin > zj * (1.0 + tol):  # the view sees a surface behind the point: free space
                    contra += 1
                    freesp += 1
                elif wmin < zj * (1.0 - tol):  # the view sees a surface in front of it: hidden there
                    hidden += 1
            elif near[offs[j] + p] == 0:
                # nothing matched anywhere near: background, if a pair of this view could have matched it
                for m in range(V):
                    if adj[j, m] and pix[m, k] >= 0:
                        pm = pix[m, k]
                        _, wmin2 = _window(depth, nmap, offs[m], widths[m], heights[m], pm, z[m, k], nq[k],
                                             tol, -2.0, r)
                        if not (wmin2 < z[m, k] * (1.0 - tol)):  # not hidden in the partner view
                            contra += 1
                            break
        # confirmed by enough views: fewer may contradict it than agree; a pair's point alone (min_agree 0):
        # no view may contradict or hide it
        if not ((agree >= max(min_agree, 1) and contra < agree)
                or (min_agree == 0 and agree == 0 and contra == 0 and hidden == 0)):
            if freesp > 0:
                counts[2] += 1
            elif contra > 0:
                counts[3] += 1
            elif hidden > 0:
                counts[5] += 1
            else:
                counts[6] += 1
            continue
        counts[0] += 1
        if agree == 0:
            counts[1] += 1
        # merge: the fused point that observed the same pixel of one of this point's two images, at a consistent
        # depth (an agreeing view adds to the track; merging there too made 35 % fewer points on fountain-P11)
        fid = -1
        for j in (a, b):
            if not inview[j]:
                continue
            q = offs[j] + pix[j, k]
            o = owner[q]
            if o >= 0 and abs(fdepth[q] - z[j, k]) <= tol * z[j, k]:
                fid = o
                break
        if fid < 0:
            fid = n_fused[0]
            n_fused[0] += 1
        else:
            counts[4] += 1
        for c in range(3):
            sxyz[fid, c] += xyz[k, c]
            srgb[fid, c] += rgb[k, c]
            snrm[fid, c] += nrm[k, c]
        nobs[fid] += 1
        for j in range(V):
            if not inview[j]:
                continue
            track[fid, j // 64] |= np.uint64(1) << np.uint64(j % 64)
            if j != a and j != b:  # an agreeing view joins the track; only observing views claim pixels
                continue
            q = offs[j] + pix[j, k]
            if owner[q] < 0:
                owner[q] = fid
                fdepth[q] = z[j, k]
