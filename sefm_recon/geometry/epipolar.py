"""Corresponding epipolar line pairs, by rotating a line about the epipoles (paper §4.1).

Every epipolar plane contains the baseline. We parameterise the half-planes
bounded by the baseline by an angle ``phi`` about it, and a viewing ray inside a
half-plane by its angle ``alpha`` from the baseline direction ``b`` (camera 1 ->
camera 2). A half-plane cuts each image in a half-line that starts at the
epipole: that is the paper's "rotate a line about the epipole", written so that
an epipole inside the image, outside it, or at infinity (parallel lines) are all
the same code. ``alpha`` increases along both lines of a pair in the same order
as the scene points (the ordering constraint the DP relies on).

All pixel coordinates are COLMAP's (centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

logger = logging.getLogger(__name__)


@dataclass
class LinePairs:
    """Sampled corresponding epipolar lines.

    Sample ``k`` of line ``l`` in image ``n`` lies at ``start_n[l] + k * step_n[l]``
    (pixels); line ``l`` has ``count_n[l]`` samples, stored flat at
    ``offset_n[l]:offset_n[l + 1]`` in per-sample arrays.
    """

    phi: np.ndarray  #: (L,) half-plane angle of each line pair, radians
    start1: np.ndarray  #: (L, 2)
    step1: np.ndarray  #: (L, 2) about one pixel long
    count1: np.ndarray  #: (L,) int64
    start2: np.ndarray
    step2: np.ndarray
    count2: np.ndarray
    basis: np.ndarray  #: (3, 3) rows b, e_a, e_b in camera-1 axes
    phi_step: float = 0.0  #: angle between neighbouring line pairs, radians

    @property
    def offset1(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.count1)]).astype(np.int64)

    @property
    def offset2(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.count2)]).astype(np.int64)

    def __len__(self) -> int:
        return len(self.phi)

    def side(self, which: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``start`` (L, 2), ``step`` (L, 2) float64 and ``offset`` (L + 1,) of image ``which`` (1 or 2)."""
        start, step, off = (self.start1, self.step1, self.offset1) if which == 1 else (
            self.start2, self.step2, self.offset2)
        return np.ascontiguousarray(start, np.float64), np.ascontiguousarray(step, np.float64), off

    def all_points1(self) -> np.ndarray:
        """(N1, 2) positions of every sample of image 1."""
        return _expand(self.start1, self.step1, self.count1)

    def all_points2(self) -> np.ndarray:
        return _expand(self.start2, self.step2, self.count2)


def _expand(start, step, count) -> np.ndarray:
    count = np.asarray(count, np.int64)
    line = np.repeat(np.arange(len(count)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)  # index within its line
    return np.asarray(start, np.float64).reshape(-1, 2)[line] + k[:, None].astype(np.float64) * np.asarray(
        step, np.float64).reshape(-1, 2)[line]


def baseline_basis(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Orthonormal basis ``(b, e_a, e_b)`` (rows) in camera-1 axes; ``b`` points from camera 1 to 2."""
    c2 = -R.T @ t  # camera 2's centre in camera-1 coordinates
    norm = np.linalg.norm(c2)
    if norm < 1e-12:
        raise ValueError("zero baseline: epipolar geometry is undefined")
    b = c2 / norm
    helper = np.eye(3)[np.argmin(np.abs(b))]
    ea = np.cross(b, helper)
    ea /= np.linalg.norm(ea)
    eb = np.cross(b, ea)
    return np.stack([b, ea, eb])


def epipoles(K1, K2, R, t) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous epipoles (3,) in image 1 and 2 (the images of the other camera's centre)."""
    e1 = K1 @ (-R.T @ t)
    e2 = K2 @ t
    return e1, e2


def ray_angles(K: np.ndarray, Rc: np.ndarray, basis: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phi, alpha) of the viewing rays of pixels ``xy`` (N, 2).

    ``Rc`` rotates the camera's axes into camera 1's (identity for camera 1,
    ``R.T`` for camera 2).
    """

    Minv = np.ascontiguousarray(Rc @ np.linalg.inv(K))
    return _ray_angles(Minv, np.ascontiguousarray(basis, np.float64),
                       np.ascontiguousarray(xy, np.float64).reshape(-1, 2))


def _border(width: int, height: int, n: int = 64) -> np.ndarray:
    """Points on the rectangle of pixel centres, (4n, 2)."""
    x0, y0, x1, y1 = 0.5, 0.5, width - 0.5, height - 0.5
    s = np.linspace(0, 1, n, endpoint=False)
    return np.concatenate([
        np.c_[x0 + s * (x1 - x0), np.full(n, y0)],
        np.c_[np.full(n, x1), y0 + s * (y1 - y0)],
        np.c_[x1 - s * (x1 - x0), np.full(n, y1)],
        np.c_[np.full(n, x0), y1 - s * (y1 - y0)],
    ])


def _contains(e: np.ndarray, width: int, height: int) -> bool:
    """True when the homogeneous point e (an epipole or its antipode) lies in the image."""
    if abs(e[2]) < 1e-12:
        return False
    x, y = e[0] / e[2], e[1] / e[2]
    return 0.0 <= x <= width and 0.0 <= y <= height


def _phi_arc(phi: np.ndarray, full: bool) -> tuple[float, float]:
    """Smallest arc (start, length) containing all angles ``phi`` (or the full circle)."""
    if full:
        return -np.pi, 2 * np.pi
    p = np.sort(np.mod(phi, 2 * np.pi))
    gaps = np.diff(np.r_[p, p[0] + 2 * np.pi])
    k = int(np.argmax(gaps))
    start = p[(k + 1) % len(p)]
    return float(start), float(2 * np.pi - gaps[k])


def phi_steps(K, Rc, basis, points, spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(phi, step)`` (N,) at image points (N, 2) of a camera: the half-plane angle
    through each, and the turn of it (radians) that moves its line ``spacing`` px there
    (its gradient over half-pixel differences)."""
    phi0, _ = ray_angles(K, Rc, basis, points)
    phix, _ = ray_angles(K, Rc, basis, points + [0.5, 0.0])
    phiy, _ = ray_angles(K, Rc, basis, points + [0.0, 0.5])
    wrap = lambda d: np.abs((d + np.pi) % (2 * np.pi) - np.pi)  # noqa: E731
    return phi0, spacing * np.hypot(wrap(phix - phi0), wrap(phiy - phi0)) / 0.5


def _phi_step(K, Rc, basis, width, height, spacing) -> float:
    """Largest phi step that keeps neighbouring lines within ``spacing`` px on the image border."""
    step = phi_steps(K, Rc, basis, _border(width, height, 256), spacing)[1]
    return float(np.min(step[step > 0]))


def _clip_half_lines(K, Rc, basis, phi, width, height):
    """Clip the half-lines of half-planes ``phi`` to an image; ordered by increasing alpha.

    Returns start (L, 2), end (L, 2), ok (L,) bool.
    """
    b = basis[0]
    m = np.cos(phi)[:, None] * basis[1] + np.sin(phi)[:, None] * basis[2]  # in-plane normal to b
    n = np.cross(b[None, :], m)  # plane normal, camera-1 axes
    Kinv = np.linalg.inv(K)
    # Plane normal and in-plane direction seen from this camera: a ray r (camera axes)
    # lies in the plane iff (Rc r).n = 0, i.e. r.(Rc^T n) = 0.
    n_cam = n @ Rc
    m_cam = m @ Rc
    b_cam = b @ Rc
    line = n_cam @ Kinv  # (L, 3) homogeneous image lines: line . [x, y, 1] = 0
    a_, b_, c_ = line[:, 0], line[:, 1], line[:, 2]
    norm = np.hypot(a_, b_)
    ok = norm > 1e-15
    norm = np.where(ok, norm, 1.0)
    centre = np.array([width / 2.0, height / 2.0])
    dist = (a_ * centre[0] + b_ * centre[1] + c_) / norm
    p0 = centre[None, :] - (dist / norm)[:, None] * np.c_[a_, b_]
    d = np.c_[-b_, a_] / norm[:, None]
    lo = np.full(len(phi), -np.inf)
    hi = np.full(len(phi), np.inf)
    bounds = ((0.5, width - 0.5), (0.5, height - 0.5))
    for axis in range(2):
        vmin, vmax = bounds[axis]
        da = d[:, axis]
        par = np.abs(da) < 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (vmin - p0[:, axis]) / da
            t2 = (vmax - p0[:, axis]) / da
        tmin = np.where(par, -np.inf, np.minimum(t1, t2))
        tmax = np.where(par, np.inf, np.maximum(t1, t2))
        inside = (p0[:, axis] >= vmin) & (p0[:, axis] <= vmax)
        ok &= ~par | inside
        lo = np.maximum(lo, tmin)
        hi = np.minimum(hi, tmax)
    ok &= hi > lo
    # Keep the half of the line inside the half-plane: s(tau) = m . ray(p(tau)) > 0,
    # affine in tau; it changes sign at the epipole.
    mK = m_cam @ Kinv  # s(p) = mK . [x, y, 1]
    s0 = np.sum(mK[:, :2] * p0, axis=1) + mK[:, 2]
    sd = np.sum(mK[:, :2] * d, axis=1)
    eps = 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        tz = -s0 / sd
    pos = sd > eps
    neg = sd < -eps
    lo = np.where(pos, np.maximum(lo, tz), lo)
    hi = np.where(neg, np.minimum(hi, tz), hi)
    flat = ~pos & ~neg
    ok &= ~flat | (s0 > 0)
    ok &= hi - lo > 1.0  # at least two samples a pixel apart
    lo = np.where(ok, lo, 0.0)
    hi = np.where(ok, hi, 0.0)
    start = p0 + lo[:, None] * d
    end = p0 + hi[:, None] * d
    # Order by alpha (the angle from b): alpha increases as the ray turns away from b.
    bK = b_cam @ Kinv

    def alpha(p):
        sm = np.sum(mK[:, :2] * p, axis=1) + mK[:, 2]
        sb = p @ bK[:2] + bK[2]
        return np.arctan2(sm, sb)

    # Compare inside the segment: at the epipole itself alpha is 0 or pi, where
    # atan2 is ill-conditioned.
    swap = alpha(0.75 * start + 0.25 * end) > alpha(0.25 * start + 0.75 * end)
    start2 = np.where(swap[:, None], end, start)
    end2 = np.where(swap[:, None], start, end)
    return start2, end2, ok


def line_pairs(
    K1: np.ndarray,
    K2: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    size1: tuple[int, int],
    size2: tuple[int, int],
    line_spacing: float = 1.0,
    sample_spacing: float = 1.0,
    max_lines: int = 20000,
) -> LinePairs:
    """Corresponding epipolar line pairs that cross both images (paper §4.1).

    Args:
        K1, K2: (3, 3) pinhole matrices of the working images.
        R, t: cam2_from_cam1.
        size1, size2: (width, height) of the images.
        line_spacing: wanted distance between neighbouring lines at the far
            image border, pixels (the largest gap over both images).
        sample_spacing: distance between samples along a line, pixels.
    """
    basis = baseline_basis(R, t)
    Rc2 = R.T
    e1, e2 = epipoles(K1, K2, R, t)
    arcs = []
    for K, Rc, (w, h), e in ((K1, np.eye(3), size1, e1), (K2, Rc2, size2, e2)):
        phi_b, _ = ray_angles(K, Rc, basis, _border(w, h))
        arcs.append(_phi_arc(phi_b, full=_contains(e, w, h)))
    step = min(
        _phi_step(K1, np.eye(3), basis, *size1, line_spacing),
        _phi_step(K2, Rc2, basis, *size2, line_spacing),
    )
    start, length = arcs[0]
    n = int(np.ceil(length / step)) + 1
    if n > max_lines:
        logger.warning("capping epipolar lines at %d (wanted %d)", max_lines, n)
        n = max_lines
    phi = start + (np.arange(n) + 0.5) * (length / n)
    s1, t1, ok1 = _clip_half_lines(K1, np.eye(3), basis, phi, *size1)
    s2, t2, ok2 = _clip_half_lines(K2, Rc2, basis, phi, *size2)
    ok = ok1 & ok2
    s1, t1, s2, t2, phi = s1[ok], t1[ok], s2[ok], t2[ok], phi[ok]
    len1 = np.linalg.norm(t1 - s1, axis=1)
    len2 = np.linalg.norm(t2 - s2, axis=1)
    c1 = np.floor(len1 / sample_spacing).astype(np.int64) + 1
    c2 = np.floor(len2 / sample_spacing).astype(np.int64) + 1
    step1 = (t1 - s1) / len1[:, None] * sample_spacing
    step2 = (t2 - s2) / len2[:, None] * sample_spacing
    logger.info(
        "epipolar lines: %d pairs, %d + %d samples (epipoles %s, %s)",
        len(phi), c1.sum(), c2.sum(), _fmt_epipole(e1), _fmt_epipole(e2),
    )
    return LinePairs(phi, s1, step1, c1, s2, step2, c2, basis, float(length / n))


def _fmt_epipole(e: np.ndarray) -> str:
    if abs(e[2]) < 1e-9 * np.linalg.norm(e):
        return "at infinity"
    return f"({e[0] / e[2]:.1f}, {e[1] / e[2]:.1f})"


def line_alphas(lp: LinePairs, K: np.ndarray, Rc: np.ndarray, which: int) -> np.ndarray:
    """Angle from the baseline of the ray of every sample of image ``which``, flat (N,).

    ``Rc`` rotates the camera's axes into camera 1's (identity for camera 1,
    ``R.T`` for camera 2).
    """

    start, step, off = lp.side(which)
    Minv = np.ascontiguousarray(Rc @ np.linalg.inv(K))
    return _line_alphas(start, step, off, Minv, np.ascontiguousarray(lp.basis, np.float64))


def sample_line_channels(image: np.ndarray, lp: LinePairs, K: np.ndarray, Rc: np.ndarray, which: int,
                         neighbours: int = 0, neighbour_step: float = 1.0) -> np.ndarray:
    """Bilinear samples of every line of image ``which`` and of its neighbour lines.

    Sample k of line l is the ray (phi_l, alpha_k); its neighbour ``o`` is the ray
    (phi_l + o * neighbour_step * phi_step, alpha_k), o = -neighbours..neighbours.
    Neighbours are aligned across lines in both images, so a surface point's
    partner moves little from one to the next: stacking them gives the 1-D
    matcher a small 2-D window.

    Args:
        image: (H, W) or (H, W, C); sampled as float32.
        K, Rc: the camera's pinhole matrix, and the rotation from its axes into
            camera 1's (identity for camera 1, ``R.T`` for camera 2).
    Returns:
        (N, (2 neighbours + 1) C) float32, neighbour-major then channel.
    """

    start, step, off = lp.side(which)
    img = np.ascontiguousarray(image, np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    offsets = np.arange(-neighbours, neighbours + 1) * neighbour_step * lp.phi_step
    Minv = np.ascontiguousarray(Rc @ np.linalg.inv(K))  # homogeneous pixel -> camera-1-axes ray
    M = np.ascontiguousarray(K @ Rc.T)  # and back
    return _sample_line_channels(img, start, step, off, np.ascontiguousarray(lp.phi, np.float64),
                                 offsets.astype(np.float64), np.ascontiguousarray(lp.basis, np.float64), Minv, M)


def sample_lines(image: np.ndarray, start: np.ndarray, step: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` along lines, flat (sum(count), C) float32.

    Args:
        image: (H, W) or (H, W, C), any dtype; sampled as float32.
    """

    img = np.ascontiguousarray(image, np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    count = np.asarray(count, np.int64).reshape(-1)
    off = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
    L = len(count)
    return _sample_line_channels(img, np.ascontiguousarray(start, np.float64).reshape(L, 2),
                                 np.ascontiguousarray(step, np.float64).reshape(L, 2), off, np.zeros(L), np.zeros(1),
                                 np.eye(3), np.eye(3), np.eye(3))


# ------------------------------------------------------------------ numba kernels
#
# Sample ``k`` of line ``l`` lies at ``start[l] + k * step[l]`` (COLMAP pixels); line ``l``'s
# samples are stored flat at ``off[l]:off[l + 1]``. Lines are independent, so every line
# kernel runs ``prange`` over lines and writes only its own slice; the point kernels run
# ``prange`` over points.


@njit(cache=True)
def pixel_ray(Minv, x, y):
    """Ray ``Minv @ (x, y, 1)`` of a pixel, unnormalised (camera-1 axes when ``Minv = Rc K^-1``)."""
    r0 = Minv[0, 0] * x + Minv[0, 1] * y + Minv[0, 2]
    r1 = Minv[1, 0] * x + Minv[1, 1] * y + Minv[1, 2]
    r2 = Minv[2, 0] * x + Minv[2, 1] * y + Minv[2, 2]
    return r0, r1, r2


@njit(parallel=True, cache=True)
def _ray_angles(Minv, basis, xy):
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
def _line_alphas(start, step, off, Minv, basis):
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
def _sample_line_channels(img, start, step, off, phi, offsets, basis, Minv, M):
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
