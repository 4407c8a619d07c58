"""The disparities of the line images read back at every pixel of image 1.

Each pixel centre's own ray gives its fractional row and column of the line images, the
disparity there (interpolated over the cells on the nearest one's surface) its ray in
image 2, so every pixel holds one match exactly on its epipolar line whatever the sampling
of the line images, and its scene point where the two rays meet (:func:`pixel_matches`).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..geometry.epipolar import pixel_ray
from ..geometry.two_view import TwoView
from .lines import LineGrid, project_polar
from .surfaces import SAME_SURFACE_COLUMNS

__all__ = ["GridScalars", "pixel_matches"]

#: Pixels of image 1 read back at a time: bounds the per-pixel arrays to about 100 MB.
_CHUNK_PIXELS = 1 << 20


class GridScalars(NamedTuple):
    """What :func:`_read_back` needs of a :class:`.lines.LineGrid` and the disparity map."""

    phi0: float  #: ``phi`` of row 0, radians (the rows' angles rise from it)
    u_max: float
    u_step: float
    pad: float
    edge: float
    min_disparity: float  #: disparities below this are invalid
    interpolate: bool  #: over the cells on the nearest one's surface (else the nearest cell's)


@njit(parallel=True, cache=True)
def _read_back(disp, xs, reach, joined, g, basis, K1inv, P2, baseline, w1, y0, w2, h2, uv2, X, cell):
    """For pixel ``i`` of image 1 (column ``i % w1``, row ``y0 + i // w1``): its ray's
    ``(phi, alpha)``, the disparity of the line images at its fractional row and
    column, interpolated over the neighbours on the nearest cell's surface, the
    position in image 2 of the ray at that parallax in the pixel's own half-plane, and
    the scene point where the two rays meet. Writes ``uv2`` (N, 2), ``X`` (N, 3) (camera
    1's frame) and ``cell`` (N,), the nearest cell's flat index in ``disp`` (-1: no match).

    Both rays lie in the half-plane: the point lies at ``baseline * sin(alpha2) /
    sin(alpha2 - alpha1)`` along the pixel's ray (the law of sines in the triangle of
    the two centres and the point), where the midpoint triangulation of the pair would
    put it, without its pass over the matches (0.19 s on the bench pair). Rays within
    1e-6 of parallel (as there) get no match.

    The cell nearest the pixel sets the surface (the pixel is unmatched when it is
    invalid: the matcher's checks rejected it). ``xs`` (rows,) the rows' ``phi`` less
    ``g.phi0`` (rising), ``reach`` and ``joined`` the grid's (:class:`.lines.LineGrid`);
    ``K1inv`` (3, 3) maps pixels to rays; ``P2`` (3, 3) = ``K2 R`` projects
    camera-1-axes rays into image 2.
    """
    n = cell.shape[0]
    H, W = disp.shape
    two_pi = 2.0 * np.pi
    last = H - 1
    circle = joined[last]  # the rows go all round the epipole
    # Each ray's alpha is handled by its half-angle tangent tan(alpha / 2): it gives the
    # column (its log), the test against the epipole margin (alpha within ``edge`` of 0 or
    # pi) and image 2's ray (alpha's cosine and sine) without trigonometric calls: the
    # read-back took 0.21 s on the bench pair with them, 0.12 s without.
    t_lo = np.tan(0.5 * g.edge)
    t_hi = 1.0 / t_lo
    for i in prange(n):
        cell[i] = -1
        r0, r1, r2 = pixel_ray(K1inv, i % w1 + 0.5, y0 + i // w1 + 0.5)
        rb = r0 * basis[0, 0] + r1 * basis[0, 1] + r2 * basis[0, 2]
        ra = r0 * basis[1, 0] + r1 * basis[1, 1] + r2 * basis[1, 2]
        re = r0 * basis[2, 0] + r1 * basis[2, 1] + r2 * basis[2, 2]
        rho = np.sqrt(ra * ra + re * re)
        if rho <= 0.0:
            continue
        nr = np.sqrt(rho * rho + rb * rb)
        th = rho / (nr + rb) if rb >= 0.0 else (nr - rb) / rho  # tan(alpha / 2), either form stable
        if th < t_lo or th > t_hi:
            continue
        phi = np.arctan2(re, ra)
        c = g.pad + (g.u_max - np.log(th)) / g.u_step
        x = phi - g.phi0
        x -= two_pi * np.floor(x / two_pi)
        if not circle and x > 0.5 * (xs[last] + two_pi):  # just below row 0, not past the last row
            x -= two_pi
        # the rows about the ray: q0 at or below it, q1 above (the first, 2 pi on, after the last)
        q0 = np.searchsorted(xs, x, side="right") - 1
        q1 = q0 + 1
        x0 = xs[q0] if q0 >= 0 else 0.0
        x1 = xs[q1] if q1 <= last else two_pi  # (xs[0] = 0)
        if q1 > last:
            q1 = 0 if circle else -1
        if q0 >= 0 and q1 >= 0 and joined[q0]:
            wk = (x - x0) / (x1 - x0)
        else:
            # a gap between rows, or beyond the first or last: the first and last rows
            # lie half a row inside image 1's outermost pixel centres, which are as near
            # the row beyond that does not exist; a row's cells reach its spacing
            # (``reach``) beyond it, and the nearer row that reaches the ray takes it
            if q0 >= 0 and x - x0 > reach[q0]:
                q0 = -1
            if q1 >= 0 and x1 - x > reach[q1]:
                q1 = -1
            wk = 0.0 if q0 >= 0 and (q1 < 0 or x - x0 <= x1 - x) else 1.0
        c0 = int(np.floor(c))
        wc = c - c0
        # the cell nearest the pixel sets the surface: where the matcher rejected it
        # (left-right check, uniqueness, speckle), the pixel stays unmatched
        rn = q0 if (wk < 0.5 and q0 >= 0) or q1 < 0 else q1
        cn = c0 + (1 if wc >= 0.5 else 0)
        if rn < 0 or cn < 0 or cn >= W or disp[rn, cn] < g.min_disparity:
            continue
        dn = disp[rn, cn]
        num = 0.0
        den = 0.0
        for j in range(4):
            rr = q0 if j < 2 else q1
            cc = c0 + (j & 1)
            w = (1.0 - wk if j < 2 else wk) * (1.0 - wc if (j & 1) == 0 else wc)
            if rr < 0 or cc < 0 or cc >= W:
                continue
            v = disp[rr, cc]
            if v >= g.min_disparity and abs(v - dn) <= SAME_SURFACE_COLUMNS:
                num += w * v
                den += w
        d = num / den if den > 0.0 and g.interpolate else dn
        # image 2's ray: tan(alpha2 / 2) from the column, its cosine and sine from that
        t2 = np.exp(g.u_max - (c - d - g.pad) * g.u_step)
        if t2 > 1.0:
            t2 = 1.0 / t2
            ca2 = (t2 * t2 - 1.0) / (t2 * t2 + 1.0)
        else:
            ca2 = (1.0 - t2 * t2) / (1.0 + t2 * t2)
        sa2 = 2.0 * t2 / (1.0 + t2 * t2)
        u, v, z = project_polar(P2, basis, ra / rho, re / rho, ca2, sa2)
        if z <= 1e-9:
            continue
        if u < 0.0 or u >= w2 or v < 0.0 or v >= h2:
            continue
        sd = sa2 * rb / nr - ca2 * rho / nr  # sin(alpha2 - alpha1)
        if sd <= 1e-6:
            continue
        s = baseline * sa2 / (sd * nr)  # the distance along the ray, over the ray's length
        uv2[i, 0] = u
        uv2[i, 1] = v
        X[i, 0] = r0 * s
        X[i, 1] = r1 * s
        X[i, 2] = r2 * s
        cell[i] = rn * W + cn


@njit(parallel=True, cache=True)
def _compact(uv2, X, cell, w, y0, out1, out2, out_X, out_c, m0):
    """The matched pixels of a chunk (``cell >= 0``) in pixel order, packed into ``out1``,
    ``out2`` (M, 2), ``out_X`` (M, 3) and ``out_c`` (M,) from index ``m0``: one parallel
    pass per image row (counting, then writing at each row's offset). Returns the index
    after the last."""
    nrows = cell.shape[0] // w
    count = np.zeros(nrows + 1, np.int64)
    for r in prange(nrows):
        c = 0
        for j in range(r * w, (r + 1) * w):
            if cell[j] >= 0:
                c += 1
        count[r + 1] = c
    start = np.cumsum(count) + m0
    for r in prange(nrows):
        m = start[r]
        for j in range(r * w, (r + 1) * w):
            if cell[j] >= 0:
                out1[m, 0] = j - r * w + 0.5
                out1[m, 1] = y0 + r + 0.5
                out2[m, 0] = uv2[j, 0]
                out2[m, 1] = uv2[j, 1]
                out_X[m, 0] = X[j, 0]
                out_X[m, 1] = X[j, 1]
                out_X[m, 2] = X[j, 2]
                out_c[m] = cell[j]
                m += 1
    return start[-1]


def pixel_matches(disp: np.ndarray, min_disparity: float, grid: LineGrid, tv: TwoView,
                  size1: tuple[int, int], size2: tuple[int, int], interpolate: bool = True):
    """One match per pixel of image 1 from a disparity map of the line images.

    ``disp`` (rows, width) float32 disparities in columns (``x2 = x1 - d``), invalid
    below ``min_disparity``. Each pixel centre's ray gives its fractional row and
    column; the disparity there is interpolated over the four cells around it that lie
    on the surface of the nearest one (within :data:`.surfaces.SAME_SURFACE_COLUMNS`), and the match is the
    ray at that parallax in the pixel's own half-plane, so it lies exactly on the
    pixel's epipolar line. Pixels nearer an epipole than ``grid.edge``, whose nearest cell
    is invalid, or whose match leaves image 2 get none.

    Returns ``(uv1, uv2, X, cells)``: (N, 2) COLMAP positions, (N, 3) their scene points
    (camera 1's frame, in front of both cameras) and (N,) int64 the flat index in ``disp``
    of each match's nearest cell (its line image row ``cells // width``), each the leading
    slice of an array of one row a pixel of image 1 (the room after it takes matches
    appended later without a copy, :func:`sefm_recon.arrays.append_rows`).
    """
    xs = np.ascontiguousarray(grid.phi - grid.phi[0], np.float64)
    reach = np.ascontiguousarray(grid.reach, np.float64)
    joined = np.ascontiguousarray(grid.joined, np.bool_)
    g = GridScalars(float(grid.phi[0]), float(grid.u_max), float(grid.u_step), float(grid.pad), float(grid.edge),
                    float(min_disparity), bool(interpolate))
    P2 = np.ascontiguousarray(tv.K2 @ tv.R)
    basis = np.ascontiguousarray(grid.basis, np.float64)
    K1inv = np.ascontiguousarray(np.linalg.inv(tv.K1))
    w, h = size1
    rows_per_chunk = max(1, _CHUNK_PIXELS // w)
    # numpy's outputs, one match a pixel at most, filled chunk by chunk and cut at the end
    # (arrays of numba's or a concatenation cost their size in fresh pages twice over)
    out1, out2, out_c = np.empty((w * h, 2)), np.empty((w * h, 2)), np.empty(w * h, np.int64)
    out_X = np.empty((w * h, 3))
    uv2 = np.empty((min(h, rows_per_chunk) * w, 2))
    X = np.empty((min(h, rows_per_chunk) * w, 3))
    cell = np.empty(min(h, rows_per_chunk) * w, np.int64)
    baseline = float(np.linalg.norm(tv.t))
    m = 0
    for y0 in range(0, h, rows_per_chunk):
        n = w * (min(h, y0 + rows_per_chunk) - y0)
        _read_back(disp, xs, reach, joined, g, basis, K1inv, P2, baseline, w, y0, float(size2[0]), float(size2[1]),
                   uv2[:n], X[:n], cell[:n])
        m = _compact(uv2[:n], X[:n], cell[:n], w, y0, out1, out2, out_X, out_c, m)
    return out1[:m], out2[:m], out_X[:m], out_c[:m]
