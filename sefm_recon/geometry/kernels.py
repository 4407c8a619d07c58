"""numba kernels of the two-view geometry: epipolar line sampling, ray angles, triangulation.

Sample ``k`` of line ``l`` lies at ``start[l] + k * step[l]`` (COLMAP pixels);
line ``l``'s samples are stored flat at ``off[l]:off[l + 1]``. Lines are
independent, so every line kernel runs ``prange`` over lines and writes only its
own slice; the point kernels run ``prange`` over points.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange


@njit(cache=True)
def pixel_ray(Minv, x, y):
    """Ray ``Minv @ (x, y, 1)`` of a pixel, unnormalised (camera-1 axes when ``Minv = Rc K^-1``)."""
    r0 = Minv[0, 0] * x + Minv[0, 1] * y + Minv[0, 2]
    r1 = Minv[1, 0] * x + Minv[1, 1] * y + Minv[1, 2]
    r2 = Minv[2, 0] * x + Minv[2, 1] * y + Minv[2, 2]
    return r0, r1, r2


@njit(parallel=True, cache=True)
def ray_angles(Minv, basis, xy):
    """(phi, alpha) of pixel rays, (N,) float64 each, radians; see :func:`sefm_recon.geometry.epipolar.ray_angles`.

    ``Minv`` (3, 3) maps homogeneous pixels to rays in camera-1 axes (``Rc K^-1``);
    ``basis`` rows are ``(b, e_a, e_b)``; ``xy`` (N, 2) COLMAP pixels.
    """
    n = xy.shape[0]
    phi = np.empty(n)
    alpha = np.empty(n)
    for k in prange(n):
        r0, r1, r2 = pixel_ray(Minv, xy[k, 0], xy[k, 1])
        rb = r0 * basis[0, 0] + r1 * basis[0, 1] + r2 * basis[0, 2]
        ra = r0 * basis[1, 0] + r1 * basis[1, 1] + r2 * basis[1, 2]
        re = r0 * basis[2, 0] + r1 * basis[2, 1] + r2 * basis[2, 2]
        phi[k] = np.arctan2(re, ra)
        alpha[k] = np.arctan2(np.sqrt(ra * ra + re * re), rb)
    return phi, alpha


@njit(parallel=True, cache=True)
def line_alphas(start, step, off, Minv, basis):
    """Angle from the baseline of every sample's viewing ray, (N,) float64.

    ``Minv`` (3, 3) maps homogeneous pixels to rays in camera-1 axes (``Rc K^-1``);
    ``basis`` rows are ``(b, e_a, e_b)``.
    """
    L = off.shape[0] - 1
    alpha = np.empty(off[L])
    for ll in prange(L):
        l = np.int64(ll)
        for k in range(off[l + 1] - off[l]):
            r0, r1, r2 = pixel_ray(Minv, start[l, 0] + k * step[l, 0], start[l, 1] + k * step[l, 1])
            rb = r0 * basis[0, 0] + r1 * basis[0, 1] + r2 * basis[0, 2]
            ra = r0 * basis[1, 0] + r1 * basis[1, 1] + r2 * basis[1, 2]
            re = r0 * basis[2, 0] + r1 * basis[2, 1] + r2 * basis[2, 2]
            alpha[off[l] + k] = np.arctan2(np.sqrt(ra * ra + re * re), rb)
    return alpha


@njit(cache=True, inline="always")
def bilinear(img, x, y, c):
    """Bilinear sample of channel ``c`` of img (H, W, C) at COLMAP position (x, y), border replicated."""
    H, W = img.shape[0], img.shape[1]
    px = x - 0.5
    py = y - 0.5
    fx0 = np.floor(px)
    fy0 = np.floor(py)
    x0 = int(fx0)
    y0 = int(fy0)
    fx = px - fx0
    fy = py - fy0
    if x0 >= 0 and y0 >= 0 and x0 < W - 1 and y0 < H - 1:  # inside: no clamping (most samples)
        xa, xb, ya, yb = x0, x0 + 1, y0, y0 + 1
    else:
        xa = min(max(x0, 0), W - 1)
        xb = min(max(x0 + 1, 0), W - 1)
        ya = min(max(y0, 0), H - 1)
        yb = min(max(y0 + 1, 0), H - 1)
    # In float64, so that integer images do not wrap in the differences.
    a = np.float64(img[ya, xa, c])
    b = np.float64(img[yb, xa, c])
    top = a + fx * (np.float64(img[ya, xb, c]) - a)
    bot = b + fx * (np.float64(img[yb, xb, c]) - b)
    return top + fy * (bot - top)


@njit(parallel=True, cache=True)
def sample_line_channels(img, start, step, off, phi, offsets, basis, Minv, M):
    """Bilinear samples of each line and of its neighbour lines at the same ray angles.

    Sample ``k`` of line ``l`` is the ray ``(phi[l], alpha_k)``; its neighbour
    ``o`` is the ray ``(phi[l] + offsets[o], alpha_k)``: the same components along
    and normal to the baseline ``b``, the normal one turned about ``b``.
    ``Minv`` (``Rc K^-1``) maps pixels to rays in camera-1 axes, ``M``
    (``K Rc^T``) back. An offset of 0 is the line itself; a neighbour ray behind
    the camera takes the line's own position.

    Args:
        img: (H, W, C) float32.
        offsets: (O,) half-plane angle offsets, radians.
    Returns:
        (N, O * C) float32, neighbour-major then channel.
    """
    L = off.shape[0] - 1
    C = img.shape[2]
    O = offsets.shape[0]
    out = np.empty((off[L], O * C), np.float32)
    for ll in prange(L):
        l = np.int64(ll)
        base = off[l]
        n = off[l + 1] - base
        # The ray of sample k is r_a + k r_s; its components along b (rb) and
        # along the line's half-plane normal (rp) are linear in k too, so each
        # neighbour's ray rb b + rp m_o, and its pixel, is a projective map
        # of k: six numbers per neighbour instead of a ray per sample.
        ra0, ra1, ra2 = pixel_ray(Minv, start[l, 0], start[l, 1])
        re0, re1, re2 = pixel_ray(Minv, start[l, 0] + step[l, 0], start[l, 1] + step[l, 1])
        rs0, rs1, rs2 = re0 - ra0, re1 - ra1, re2 - ra2
        cp = np.cos(phi[l])
        sp = np.sin(phi[l])
        m0 = cp * basis[1, 0] + sp * basis[2, 0]
        m1 = cp * basis[1, 1] + sp * basis[2, 1]
        m2 = cp * basis[1, 2] + sp * basis[2, 2]
        rb_a = ra0 * basis[0, 0] + ra1 * basis[0, 1] + ra2 * basis[0, 2]
        rb_s = rs0 * basis[0, 0] + rs1 * basis[0, 1] + rs2 * basis[0, 2]
        rp_a = ra0 * m0 + ra1 * m1 + ra2 * m2
        rp_s = rs0 * m0 + rs1 * m1 + rs2 * m2
        proj = np.empty((O, 6))  # x, y and z of M d, at k = 0 and per unit k
        for o in range(O):
            co = np.cos(phi[l] + offsets[o])
            so = np.sin(phi[l] + offsets[o])
            for i in range(3):
                da = 0.0
                ds = 0.0
                for j in range(3):
                    mo = co * basis[1, j] + so * basis[2, j]
                    da += M[i, j] * (rb_a * basis[0, j] + rp_a * mo)
                    ds += M[i, j] * (rb_s * basis[0, j] + rp_s * mo)
                proj[o, i] = da
                proj[o, 3 + i] = ds
        for k in range(n):
            x0 = start[l, 0] + k * step[l, 0]
            y0 = start[l, 1] + k * step[l, 1]
            for o in range(O):
                z = proj[o, 2] + k * proj[o, 5]
                x, y = x0, y0  # a neighbour ray behind the camera takes the line's own pixel
                if offsets[o] != 0.0 and z > 0:
                    x = (proj[o, 0] + k * proj[o, 3]) / z
                    y = (proj[o, 1] + k * proj[o, 4]) / z
                for c in range(C):
                    out[base + k, o * C + c] = bilinear(img, x, y, c)
    return out


@njit(cache=True)
def _first_at_least(a, s, e, v):
    """First index i in [s, e) with a[i] >= v (a sorted), e if none."""
    while s < e:
        m = (s + e) >> 1
        if a[m] < v:
            s = m + 1
        else:
            e = m
    return s


@njit(cache=True)
def _first_above(a, s, e, v):
    """First index i in [s, e) with a[i] > v (a sorted), e if none."""
    while s < e:
        m = (s + e) >> 1
        if a[m] <= v:
            s = m + 1
        else:
            e = m
    return s


@njit(cache=True)
def _gallop(a, s, e, v, guess, strict):
    """:func:`_first_at_least` (``strict``: :func:`_first_above`), searching out from ``guess``.

    Neighbouring samples have nearby bands, so the answer is most often a
    step or two from the previous one: widen a bracket around ``guess``
    by doubling, then bisect inside it.
    """
    g = min(max(guess, s), e)
    step = 1
    if g == e or (a[g] > v if strict else a[g] >= v):  # the answer is at or below g
        hi = g
        lo = g - step
        while lo > s and (a[lo] > v if strict else a[lo] >= v):
            hi = lo
            step *= 2
            lo = g - step
        lo = max(lo, s)
    else:  # the answer is above g
        lo = min(g + 1, e)
        hi = min(g + step, e)
        while hi < e and not (a[hi] > v if strict else a[hi] >= v):
            lo = hi + 1
            step *= 2
            hi = min(g + step, e)
    if strict:
        return _first_above(a, lo, hi, v)
    return _first_at_least(a, lo, hi, v)


@njit(cache=True)
def sample_band(alpha1, a2, s2, e2, dmin, dmax, baseline, slack, ga, gb):
    """Line-2 band of one line-1 sample of ray angle ``alpha1`` (see :func:`depth_band`).

    ``a2[s2:e2]`` is line 2; ``ga``, ``gb`` are the previous sample's search
    answers (absolute indices), where the search starts. Returns ``lo, hi,
    ga, gb``.
    """
    sa = np.sin(alpha1)
    ca = np.cos(alpha1)
    hi_a = np.arctan2(dmin * sa, dmin * ca - baseline)
    if np.isfinite(dmax):
        lo_a = np.arctan2(dmax * sa, dmax * ca - baseline)
    else:
        lo_a = alpha1
    ga = _gallop(a2, s2, e2, lo_a, ga, False)
    gb = _gallop(a2, s2, e2, hi_a, gb, True)
    n2 = e2 - s2
    a = ga - s2 - slack
    b = gb - 1 - s2 + slack  # last index with a2 <= hi_a
    return min(max(a, 0), n2 - 1), min(max(b, -1), n2 - 1), ga, gb


@njit(parallel=True, cache=True)
def depth_band(a1, off1, a2, off2, dmin, dmax, baseline, slack, start, step, sx, sy, gmin, gmax):
    """For each line-1 sample, the line-2 sample range holding points at distances [dmin, dmax].

    A point at distance ``d`` along the ray of angle ``a1`` is seen from camera 2
    under ``a2 = atan2(d sin a1, d cos a1 - B)``, falling from pi (d = 0) to
    ``a1`` (d = inf); ``a2`` increases along each line 2.

    The range of sample ``k`` of line ``l`` (at ``start[l] + k step[l]``,
    COLMAP pixels of image 1) is cell ``floor(x sx), floor(y sy)`` of the
    ``gmin``/``gmax`` grids (a coarser level's distance range near each
    pixel) where it is finite, else ``dmin``/``dmax``. Read here and used at once, so
    no (N1,) range arrays are made: fresh memory is what a large pair pays
    most for. A 1x1 grid of inf leaves every sample its ``dmin``/``dmax``.

    Args:
        a1, a2: (N1,), (N2,) sample ray angles.
        dmin, dmax: (N1,) distance range per sample (``dmax`` may be inf;
            a broadcast view is fine).
    Returns:
        lo, hi (N1,) int64 positions on line 2 relative to its start, widened
        by ``slack`` samples and clipped (``hi < lo`` when empty).
    """
    L = off1.shape[0] - 1
    N1 = a1.shape[0]
    H, W = gmin.shape
    lo = np.empty(N1, np.int64)
    hi = np.empty(N1, np.int64)
    for ll in prange(L):
        l = np.int64(ll)
        s2 = off2[l]
        e2 = off2[l + 1]
        ga = s2
        gb = s2
        for k in range(off1[l + 1] - off1[l]):
            i = off1[l] + k
            c = min(max(int(np.floor((start[l, 0] + k * step[l, 0]) * sx)), 0), W - 1)
            r = min(max(int(np.floor((start[l, 1] + k * step[l, 1]) * sy)), 0), H - 1)
            d0 = np.float64(dmin[i])
            d1 = np.float64(dmax[i])
            if np.isfinite(gmin[r, c]):
                d0 = np.float64(gmin[r, c])
                d1 = np.float64(gmax[r, c])
            lo[i], hi[i], ga, gb = sample_band(a1[i], a2, s2, e2, d0, d1, baseline, slack, ga, gb)
    return lo, hi


@njit(parallel=True, cache=True)
def invert_band(lo, hi, off1, off2):
    """Band of line-1 positions for every line-2 sample, from the line-2 band of every line-1 sample.

    The bands are first made monotone (only ever widened): ``hi`` as a running
    maximum along the line, ``lo`` as a running minimum from its end. Line-2
    sample ``k`` may then match line-1 samples ``first..last``: the first
    whose ``hi`` reaches ``k`` and the last whose ``lo`` does not pass it.
    """
    L = off1.shape[0] - 1
    N2 = off2[L]
    first = np.empty(N2, np.int64)
    last = np.empty(N2, np.int64)
    for ll in prange(L):
        l = np.int64(ll)
        s1 = off1[l]
        n1 = off1[l + 1] - s1
        s2 = off2[l]
        n2 = off2[l + 1] - s2
        hi_m = np.empty(n1, np.int64)
        lo_m = np.empty(n1, np.int64)
        run = np.int64(-(1 << 40))
        for i in range(n1):
            run = max(run, hi[s1 + i])
            hi_m[i] = run
        run = np.int64(1 << 40)
        for i in range(n1 - 1, -1, -1):
            run = min(run, lo[s1 + i])
            lo_m[i] = run
        p = 0  # first i with hi_m[i] >= k
        q = 0  # first i with lo_m[i] > k
        for k in range(n2):
            while p < n1 and hi_m[p] < k:
                p += 1
            while q < n1 and lo_m[q] <= k:
                q += 1
            first[s2 + k] = min(max(p, 0), n1 - 1)
            last[s2 + k] = min(max(q - 1, -1), n1 - 1)
    return first, last


@njit(cache=True)
def rasterise_min_max(uv, dist, mask, gmin, gmax):
    """Lower ``gmin`` and raise ``gmax`` (H, W) to the ``dist`` of each point in ``mask``, in place.

    Point ``k`` falls in cell ``floor(uv[k])`` (COLMAP pixels of the grid's
    image); points outside the grid are skipped. Fresh grids start at inf
    and -inf.
    """
    height, width = gmin.shape
    for k in range(uv.shape[0]):
        if not mask[k]:
            continue
        c = int(np.floor(uv[k, 0]))
        r = int(np.floor(uv[k, 1]))
        if 0 <= r < height and 0 <= c < width:
            d = np.float32(dist[k])
            if d < gmin[r, c]:
                gmin[r, c] = d
            if d > gmax[r, c]:
                gmax[r, c] = d


class Midpoint(NamedTuple):
    """Midpoint of the shortest segment between two viewing rays (:func:`ray_midpoint`)."""

    x: float  #: the point, camera-1 frame
    y: float
    z: float
    s1: float  #: distance along ray 1 (unit length) to its closest point; NaN for parallel rays
    s2: float  #: the same along ray 2
    cos: float  #: cosine of the angle between the rays


@njit(cache=True)
def best_per_cell(uv, score, cell, nx, ny):
    """Index of the highest ``score`` (the first of ties) in each occupied ``cell``-px square of an
    ``nx`` x ``ny`` grid over ``uv`` (N, 2); (M,) int64, cells in x-major order. One pass: a sort
    of millions of dense matches took 0.19 s of the bench pair's."""
    best = np.full(nx * ny, -1, np.int64)
    for i in range(uv.shape[0]):
        kx = min(max(int(np.floor(uv[i, 0] / cell)), 0), nx - 1)
        ky = min(max(int(np.floor(uv[i, 1] / cell)), 0), ny - 1)
        c = kx * ny + ky
        if best[c] < 0 or score[i] > score[best[c]]:
            best[c] = i
    return best[best >= 0]


@njit(cache=True)
def ray_midpoint(Kinv1, Kinv2, Rt, c2, x1, y1, x2, y2):
    """:class:`Midpoint` of the rays of pixel (x1, y1) of camera 1 and pixel (x2, y2) of camera 2.

    ``Kinv1``, ``Kinv2`` (3, 3) inverse intrinsics; ``Rt`` (3, 3) is ``R^T``
    (camera-2 rays into camera-1 axes), ``c2`` (3,) camera 2's centre in camera 1.
    """
    a0 = Kinv1[0, 0] * x1 + Kinv1[0, 1] * y1 + Kinv1[0, 2]
    a1 = Kinv1[1, 0] * x1 + Kinv1[1, 1] * y1 + Kinv1[1, 2]
    a2 = Kinv1[2, 0] * x1 + Kinv1[2, 1] * y1 + Kinv1[2, 2]
    q0 = Kinv2[0, 0] * x2 + Kinv2[0, 1] * y2 + Kinv2[0, 2]
    q1 = Kinv2[1, 0] * x2 + Kinv2[1, 1] * y2 + Kinv2[1, 2]
    q2 = Kinv2[2, 0] * x2 + Kinv2[2, 1] * y2 + Kinv2[2, 2]
    b0 = Rt[0, 0] * q0 + Rt[0, 1] * q1 + Rt[0, 2] * q2
    b1 = Rt[1, 0] * q0 + Rt[1, 1] * q1 + Rt[1, 2] * q2
    b2 = Rt[2, 0] * q0 + Rt[2, 1] * q1 + Rt[2, 2] * q2
    na = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    nb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    a0 /= na
    a1 /= na
    a2 /= na
    b0 /= nb
    b1 /= nb
    b2 /= nb
    dot = a0 * b0 + a1 * b1 + a2 * b2
    e = a0 * c2[0] + a1 * c2[1] + a2 * c2[2]
    f = b0 * c2[0] + b1 * c2[1] + b2 * c2[2]
    den = 1.0 - dot * dot
    if den > 0.0:
        s1 = (e - dot * f) / den
        s2 = (dot * e - f) / den
    else:
        s1 = np.nan
        s2 = np.nan
    return Midpoint(0.5 * (s1 * a0 + c2[0] + s2 * b0), 0.5 * (s1 * a1 + c2[1] + s2 * b1),
                    0.5 * (s1 * a2 + c2[2] + s2 * b2), s1, s2, dot)


@njit(parallel=True, cache=True)
def triangulate_midpoint(Kinv1, Kinv2, Rt, c2, uv1, uv2, X):
    """Midpoint triangulation of pixel pairs ``uv1``, ``uv2`` (N, 2); see :func:`.triangulate.triangulate`.

    Arguments as :func:`ray_midpoint`'s; the points are written to the first N rows of
    ``X`` (at least (N, 3)), camera-1 frame. Returns valid (N,) bool (finite, in front
    of both cameras, rays not parallel) and the angle between the rays (N,), radians.
    """
    n = uv1.shape[0]
    valid = np.empty(n, np.bool_)
    angle = np.empty(n)
    for kk in prange(n):
        k = np.int64(kk)
        m = ray_midpoint(Kinv1, Kinv2, Rt, c2, uv1[k, 0], uv1[k, 1], uv2[k, 0], uv2[k, 1])
        X[k, 0], X[k, 1], X[k, 2] = m.x, m.y, m.z
        valid[k] = (np.isfinite(m.x) and np.isfinite(m.y) and np.isfinite(m.z) and m.s1 > 0.0 and m.s2 > 0.0
                    and 1.0 - m.cos * m.cos > 1e-12)
        angle[k] = np.arccos(min(1.0, max(-1.0, m.cos)))
    return valid, angle


@njit(parallel=True, cache=True)
def points_at_distance(Kinv1, K2, R, t, uv1, dist):
    """Points at distance ``dist`` (N,) along the rays of camera-1 pixels ``uv1`` (N, 2), and their camera-2 pixels.

    Camera 2 is ``x_cam2 = R X + t``. Each returned ``uv2`` lies on the
    epipolar line of its ``uv1``, whatever the distance.
    Returns X (N, 3) camera-1 frame, uv2 (N, 2).
    """
    n = uv1.shape[0]
    X = np.empty((n, 3))
    uv2 = np.empty((n, 2))
    for kk in prange(n):
        k = np.int64(kk)
        r0, r1, r2 = pixel_ray(Kinv1, uv1[k, 0], uv1[k, 1])
        s = dist[k] / np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        x0, x1, x2 = r0 * s, r1 * s, r2 * s
        X[k, 0], X[k, 1], X[k, 2] = x0, x1, x2
        y0 = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]
        y1 = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]
        y2 = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
        p0 = K2[0, 0] * y0 + K2[0, 1] * y1 + K2[0, 2] * y2
        p1 = K2[1, 0] * y0 + K2[1, 1] * y1 + K2[1, 2] * y2
        p2 = K2[2, 0] * y0 + K2[2, 1] * y1 + K2[2, 2] * y2
        uv2[k, 0] = p0 / p2
        uv2[k, 1] = p1 / p2
    return X, uv2
