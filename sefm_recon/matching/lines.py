"""Polar line images (paper §4.1): corresponding epipolar lines stacked as image rows.

Every epipolar half-plane about the baseline (angle ``phi``, the rows of
:func:`sefm_recon.geometry.epipolar.line_pairs`) cuts a line from each image. Along
it a viewing ray is given by its angle ``alpha`` from the baseline direction ``b``
(camera 1 towards camera 2). Sampling both images on the same ``(phi, alpha)`` grid
makes a pair of "line images" in which every correspondence lies on one row; a
scene point seen under ``alpha1`` from camera 1 is seen under ``alpha2 >= alpha1``
from camera 2 (the parallax angle is ``alpha2 - alpha1``). Columns run towards
smaller ``alpha``, so that a match is ``x2 = x1 - d`` with ``d >= 0``, as rectified
stereo matchers expect. Unlike a planar rectification this works whatever the
epipoles, including one inside an image (forward motion, zoom).

Columns are uniform in ``u = log tan(alpha / 2)`` (``du = dalpha / sin(alpha)``), not in
``alpha``. Near ``alpha = pi / 2`` (sideways motion) the two agree. Near an epipole
(forward motion, zoom) an image point moves away from the epipole by a factor
(``alpha2 ~ s alpha1``): in ``u`` that is a shift by ``log s`` that leaves the local
sampling alike in both line images, so a window matcher sees no scale change. A planar
rectification (``du = dalpha / sin^2(alpha)``) would send the epipole to infinity.

Pixel conventions are COLMAP's (``docs/CONVENTIONS.md``); ray directions are in
camera 1's axes, ``Rc`` rotates a camera's axes into camera 1's (``R.T`` for camera 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit, prange

from ..geometry.epipolar import line_pairs, phi_steps, ray_angles
from ..geometry.two_view import TwoView

__all__ = ["ROW_SPACING_PX", "COLUMN_SPACING_PX", "EPIPOLE_MARGIN_PX", "LineGrid", "line_grid", "pixel_grid",
           "line_images", "log_tan_half", "match_parallax", "rays", "project"]

#: Neighbouring rows are at most this far apart (px) anywhere in either image: the pixel
#: pitch, so that a 5x5 window of the line images spans 5x5 pixels, the support StereoSGBM's
#: penalties are set for (:mod:`.sgm`), and the matcher averages as much noise as the
#: planar SGBM peer. At 0.8 px (a 4x4 px window, 1.6 times the cells) the real pairs
#: gained 0.010 of precision at 1 px (coverage within 0.004), but the generated scenes,
#: with sensor noise, lost 0.029 of precision and 0.054 of coverage, and matching took
#: twice as long. No nearer either (:func:`line_grid`): rows uniform in ``phi`` at the step
#: the farthest border point needs lay 0.94 px apart on average on the bench pair and
#: 0.6 px on the forward scenes; spread by what each place needs, the generated scenes
#: gained 0.004 of precision and 0.007 of coverage at 1 px (forward and zoom most,
#: +0.006-0.036 of coverage on nine of ten), the real pairs lost 0.0014 / 0.0012 (denser
#: rows' averaging, as at 0.8 px), and a forward scene's run took 30 % less time (7.8 ->
#: 5.4 s at 1000x750).
ROW_SPACING_PX = 1.0
#: Column step as an angle of ``COLUMN_SPACING_PX / f``: one pixel at the image centre
#: (the same reasons).
COLUMN_SPACING_PX = 1.0
#: Rays closer than this to an epipole (px at the focal length) are left out: ``u`` runs to
#: infinity there, and a point that close to the epipole shows almost no parallax.
EPIPOLE_MARGIN_PX = 4.0
#: Rows resampled at a time: their maps stay near 16 MB at 4000 columns.
_BLOCK_ROWS = 512


@dataclass
class LineGrid:
    """The common ``(phi, alpha)`` grid: row ``r`` is ``phi[r]``, column ``c`` is the ray
    with ``log tan(alpha / 2) = u_max - (c - pad) * u_step``."""

    phi: np.ndarray  #: (L,) half-plane angles, radians, rising (not uniform: :func:`line_grid`)
    basis: np.ndarray  #: (3, 3) rows b, e_a, e_b in camera-1 axes
    u_max: float  #: ``log tan(alpha / 2)`` of the largest ray angle seen in image 1
    u_step: float  #: ``log tan(alpha / 2)`` per column
    columns: int  #: columns holding some ray of image 1 (after the pad)
    edge: float  #: rays within this angle (radians) of an epipole are left out (:data:`EPIPOLE_MARGIN_PX`)
    reach: np.ndarray  #: (L,) float64 angle (radians) to the row's neighbours, the larger: how far its cells reach
    joined: np.ndarray  #: (L,) bool: row ``r`` and the next (the first after the last, 2 pi on) are neighbours
    pad: int = 0  #: columns left of ``u_max`` (a matcher's search window needs them)

    def alpha(self, col) -> np.ndarray:
        """Ray angle (radians) of (fractional) columns."""
        u = self.u_max - (np.asarray(col, np.float64) - self.pad) * self.u_step
        return 2.0 * np.arctan(np.exp(u))

    def column(self, alpha) -> np.ndarray:
        """Fractional column of ray angles (radians), those nearer an epipole than ``edge``
        taken at ``edge``."""
        return self.pad + (self.u_max - log_tan_half(np.clip(alpha, self.edge, np.pi - self.edge))) / self.u_step


def log_tan_half(alpha) -> np.ndarray:
    """``log tan(alpha / 2)`` of ray angles in (0, pi): the column coordinate before scaling."""
    return np.log(np.tan(0.5 * np.asarray(alpha, np.float64)))


def match_parallax(grid: LineGrid, tv: TwoView, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(N,) float64: the parallax in the grid's columns (``x1 - x2``, image 2's line image
    unshifted: :meth:`LineGrid.column` of each ray) of matches ``uv1``, ``uv2`` (N, 2) COLMAP
    positions, each pair on one epipolar line."""
    a1 = ray_angles(tv.K1, np.eye(3), grid.basis, uv1)[1]
    a2 = ray_angles(tv.K2, tv.R.T, grid.basis, uv2)[1]
    return grid.column(a1) - grid.column(a2)


def pixel_grid(width: int, height: int, step: float = 4.0) -> np.ndarray:
    """(N, 2) COLMAP positions every ``step`` px over an image, its last row and column included."""
    xs = np.r_[np.arange(0.5, width, step), width - 0.5]
    ys = np.r_[np.arange(0.5, height, step), height - 0.5]
    X, Y = np.meshgrid(xs, ys)
    return np.column_stack([X.ravel(), Y.ravel()])


def line_grid(tv: TwoView, size1: tuple[int, int], size2: tuple[int, int], max_lines: int = 20000) -> LineGrid:
    """The rows that cover both images and the columns that cover image 1 (``size`` =
    (width, height) of each); a matcher reads image 2 at columns shifted by the parallax.

    Neighbouring rows lie :data:`ROW_SPACING_PX` apart at most anywhere in either image,
    and about that far apart where the farthest of their ends needs it (:func:`_row_angles`).

    The column step makes columns :data:`COLUMN_SPACING_PX` apart in image 1 at the
    median ray angle of its pixels (``dalpha = sin(alpha) du``).
    """
    lp = line_pairs(tv.K1, tv.K2, tv.R, tv.t, size1, size2, ROW_SPACING_PX, 1.0, max_lines)
    phi, reach, joined = _row_angles(lp, tv, size1, size2)
    f = 0.5 * float(tv.K1[0, 0] + tv.K1[1, 1])
    edge = EPIPOLE_MARGIN_PX / f
    _, alpha = ray_angles(tv.K1, np.eye(3), lp.basis, pixel_grid(*size1))
    alpha = np.clip(alpha, edge, np.pi - edge)
    step = COLUMN_SPACING_PX / f / float(np.median(np.sin(alpha)))
    u_lo, u_hi = float(log_tan_half(alpha.min())), float(log_tan_half(alpha.max()))
    return LineGrid(phi, lp.basis, u_hi, step, int(math.ceil((u_hi - u_lo) / step)) + 1, edge, reach, joined)


def _row_angles(lp, tv: TwoView, size1: tuple[int, int],
                size2: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(phi, reach, joined)`` of the rows (:class:`LineGrid`): as few as keep neighbouring
    rows :data:`ROW_SPACING_PX` apart at most anywhere in either image.

    ``lp``'s lines are uniform in ``phi``, their step set by the one place (the border
    point farthest from an epipole) where they lie farthest apart; elsewhere they lie
    nearer (the bench pair: 0.94 px apart on average, a forward motion's 0.6 px). Along
    each run of neighbouring lines the rows are spread by the cumulative share of that
    spacing each line needs, the larger of its own and its neighbour's: 1739 lines ->
    1629 rows on the bench pair, 5035 -> 2970 on a forward motion, 479 -> 417 on a real
    unrectified pair.
    """
    phi = np.asarray(lp.phi, np.float64)
    if len(phi) == 0:
        return phi, phi.copy(), np.zeros(0, bool)
    slot = np.rint((phi - phi[0]) / lp.phi_step).astype(np.int64)
    slots = int(round(2 * np.pi / lp.phi_step))
    # The lines turn about the epipole, so each moves most at its end farthest from it;
    # the farthest point of an image from it is a corner, which the lines about it pass
    # between them
    need = np.full(len(phi), np.inf)
    for which, K, Rc, (w, h) in ((1, tv.K1, np.eye(3), size1), (2, tv.K2, tv.R.T, size2)):
        start, step, off = lp.side(which)
        # the last sample lies within a step of the line's end: one step on is at or beyond it
        ends = np.concatenate([start, start + step * np.diff(off)[:, None]])
        need = np.minimum(need, phi_steps(K, Rc, lp.basis, ends, ROW_SPACING_PX)[1].reshape(2, -1).min(axis=0))
        at, corner = phi_steps(K, Rc, lp.basis, np.array([[0.5, 0.5], [w - 0.5, 0.5], [0.5, h - 0.5],
                                                          [w - 0.5, h - 0.5]]), ROW_SPACING_PX)  # pixel centres
        k = np.floor(np.mod(at - phi[0], 2 * np.pi) / lp.phi_step).astype(np.int64)  # the slot below
        for kk, c in zip(k, corner):
            near = (slot == kk) | (slot == kk + 1)
            need[near] = np.minimum(need[near], c)
    share = np.clip(lp.phi_step / np.maximum(need, 1e-300), 0.0, 1.0)  # of the row spacing, per line step
    rows, reach, joined = [], [], []
    for run in np.split(np.arange(len(phi)), np.flatnonzero(np.diff(slot) != 1) + 1):
        if len(run) == 1:
            p, r = phi[run], np.array([lp.phi_step])
        else:
            cum = np.r_[0.0, np.cumsum(np.maximum(share[run[:-1]], share[run[1:]]))]
            p = np.interp(np.linspace(0.0, cum[-1], int(math.ceil(cum[-1] - 1e-9)) + 1), cum, phi[run])
            d = np.diff(p)
            r = np.maximum(np.r_[d, d[-1]], np.r_[d[0], d])
        rows.append(p)
        reach.append(r)
        joined.append(np.r_[np.ones(len(p) - 1, bool), False])
    joined = np.concatenate(joined)
    # the lines close the circle: the last is the first's neighbour
    joined[-1] = bool(len(phi) > 1 and slot[-1] + 1 >= slots)
    return np.concatenate(rows), np.concatenate(reach).astype(np.float64), joined


def rays(basis: np.ndarray, phi, alpha) -> np.ndarray:
    """Unit ray directions (..., 3) in camera-1 axes for broadcastable ``phi``, ``alpha``."""
    phi, alpha = np.asarray(phi, np.float64), np.asarray(alpha, np.float64)
    m = np.cos(phi)[..., None] * basis[1] + np.sin(phi)[..., None] * basis[2]
    return np.cos(alpha)[..., None] * basis[0] + np.sin(alpha)[..., None] * m


def project(K: np.ndarray, Rc: np.ndarray, r: np.ndarray):
    """COLMAP positions ``(u, v, in_front)`` of camera-1-axes rays ``r`` (..., 3) in a camera."""
    p = r @ (K @ Rc.T).T
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[..., 0] / z, p[..., 1] / z, z > 1e-9


@njit(cache=True)
def project_polar(P, basis, cos_phi, sin_phi, ca, sa):
    """Pixel ``(u, v, z)`` of the camera-1-axes ray ``(phi, alpha)`` projected by ``P`` (3, 3),
    given the cosines and sines of ``phi`` and ``alpha`` (``ca``, ``sa``); ``u, v`` COLMAP
    positions, valid where ``z > 0`` (in front of the camera)."""
    x0 = ca * basis[0, 0] + sa * (cos_phi * basis[1, 0] + sin_phi * basis[2, 0])
    x1 = ca * basis[0, 1] + sa * (cos_phi * basis[1, 1] + sin_phi * basis[2, 1])
    x2 = ca * basis[0, 2] + sa * (cos_phi * basis[1, 2] + sin_phi * basis[2, 2])
    z = P[2, 0] * x0 + P[2, 1] * x1 + P[2, 2] * x2
    if z <= 1e-9:
        return 0.0, 0.0, z
    return (P[0, 0] * x0 + P[0, 1] * x1 + P[0, 2] * x2) / z, (P[1, 0] * x0 + P[1, 1] * x1 + P[1, 2] * x2) / z, z


@njit(parallel=True, cache=True)
def _remap_maps(P, basis, phi, alpha, mx, my):
    """cv2.remap's maps (float32, pixel centres at integers) of the rays ``(phi[r], alpha[c])``
    projected by ``P`` (3, 3, camera-1 axes to pixels); rays behind the camera map far outside."""
    ca, sa = np.cos(alpha), np.sin(alpha)  # each column's, once for all rows
    for r in prange(phi.shape[0]):
        cp, sp = np.cos(phi[r]), np.sin(phi[r])
        for c in range(alpha.shape[0]):
            u, v, z = project_polar(P, basis, cp, sp, ca[c], sa[c])
            if z > 1e-9:
                mx[r, c] = u - 0.5
                my[r, c] = v - 0.5
            else:
                mx[r, c] = -1e4
                my[r, c] = -1e4


@njit(parallel=True, cache=True)
def _zero_beyond(rows, mx, my, x_lo, x_hi, y_lo, y_hi, span):
    """Set the cells of ``rows`` (r, c, channels) whose map position lies outside
    ``x_lo..x_hi`` by ``y_lo..y_hi`` to 0, in place (numpy's masks took 70 ms on the bench
    pair); ``span`` (r, 2): each row's first and last cell kept, -1, -1 where none is."""
    for r in prange(rows.shape[0]):
        span[r, 0] = span[r, 1] = -1
        for c in range(rows.shape[1]):
            x = mx[r, c]
            y = my[r, c]
            if x < x_lo or x > x_hi or y < y_lo or y > y_hi:
                for k in range(rows.shape[2]):
                    rows[r, c, k] = 0
            else:
                if span[r, 0] < 0:
                    span[r, 0] = c
                span[r, 1] = c


def line_images(img1: np.ndarray, img2: np.ndarray, tv: TwoView, grid: LineGrid, width: int, shift2: int = 0,
                bicubic: bool = True, spans: bool = False, window: int = 1, frames: bool = False):
    """Both images resampled (bicubic, else bilinear) onto the grid's rows and ``width`` columns,
    image 2's shifted: its column ``c`` holds the grid's column ``c - shift2``, so that a
    match ``x2 = x1 - d`` lies at ``x1 - (d - shift2)`` in the line images.

    Returns ``(L1, L2)``, each (rows, width[, channels]) of the input dtype. Cells whose
    ray meets the image plane beyond the image's edge (COLMAP's ``0..w``, ``0..h``),
    leaves it or points behind it are 0; inside, the interpolation repeats the image's
    outermost pixels where its support reaches beyond them (no 0 mixed into the samples
    of the outer half pixel). With ``spans``, also image 2's: (rows, 2) int64 first and
    last column of each row whose cell and the cells of the ``window`` rows about it (a
    matcher's window: odd) lie between image 2's outermost pixel centres, one cell short
    of them along the row; rows beyond the line image's first and last do not count
    (first > last: none). With ``frames``, last: (2, rows, 2) int64, per image and row the
    first and last column whose ray meets the image plane within the image's frame
    (COLMAP's ``0..w`` by ``0..h``, the cells not set to 0); -1, -1 where none does.

    (Repeating the outermost pixels 2 px beyond the edge, half a window, matched the rim
    of the rect pairs, +0.0035 of coverage at 1 px, but carried SGM's depth of Plastic's
    plain panel to the border: its precision 0.855 -> 0.839 in unrect; docs/results.md.)
    """
    interpolation = cv2.INTER_CUBIC if bicubic else cv2.INTER_LINEAR
    out = []
    span2 = np.zeros((len(grid.phi), 2), np.int64)
    frame = np.zeros((2, len(grid.phi), 2), np.int64)
    own = np.zeros((len(grid.phi), width), np.uint8) if spans else None
    for k, (img, K, Rc, shift) in enumerate(((img1, tv.K1, np.eye(3), 0), (img2, tv.K2, tv.R.T, shift2))):
        alpha = grid.alpha(np.arange(width) - shift)
        L = np.zeros((len(grid.phi), width) + img.shape[2:], img.dtype)
        P = np.ascontiguousarray(K @ Rc.T)
        basis = np.ascontiguousarray(grid.basis, np.float64)
        for r0 in range(0, len(grid.phi), _BLOCK_ROWS):  # blocks of rows bound the maps' memory
            phi = np.ascontiguousarray(grid.phi[r0:r0 + _BLOCK_ROWS])
            mx = np.empty((len(phi), width), np.float32)
            my = np.empty((len(phi), width), np.float32)
            _remap_maps(P, basis, phi, alpha, mx, my)
            # Bicubic: it blurs less than bilinear where samples fall between pixels
            # (real pairs: +0.006 at 1 px).
            rows = cv2.remap(img, mx, my, interpolation, borderMode=cv2.BORDER_REPLICATE)
            h, w = img.shape[:2]
            # cv2's pixel centres are integers: COLMAP's edge 0 is -0.5
            _zero_beyond(rows.reshape(rows.shape[0], rows.shape[1], -1), mx, my, -0.5, w - 0.5, -0.5, h - 0.5,
                         frame[k, r0:r0 + len(phi)])
            L[r0:r0 + len(phi)] = rows
            if spans and k == 1:
                # samples between image 2's outermost pixel centres (their interpolation
                # reads a repeated pixel at most)
                own[r0:r0 + len(phi)] = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        out.append(L)
    if spans:
        # ...whose neighbours within the window's rows and the interpolation's pixel along
        # the row are so too; rows beyond the line image's own first and last (the image's
        # edge where the lines run along it) do not count
        inside = cv2.erode(own, np.ones((window, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                           borderValue=1).view(bool)
        # a row is a line through the epipole: its cells inside the (convex) image are one run
        any_in = inside.any(axis=1)
        span2[:, 0] = np.where(any_in, inside.argmax(axis=1), width)
        span2[:, 1] = np.where(any_in, width - 1 - inside[:, ::-1].argmax(axis=1), -1)
        out.append(span2)
    if frames:
        out.append(frame)
    return tuple(out)
