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
    from .kernels import ray_angles as kernel

    Minv = np.ascontiguousarray(Rc @ np.linalg.inv(K))
    return kernel(Minv, np.ascontiguousarray(basis, np.float64), np.ascontiguousarray(xy, np.float64).reshape(-1, 2))


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
    from .kernels import line_alphas as kernel

    start, step, off = lp.side(which)
    Minv = np.ascontiguousarray(Rc @ np.linalg.inv(K))
    return kernel(start, step, off, Minv, np.ascontiguousarray(lp.basis, np.float64))


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
    from .kernels import sample_line_channels as kernel

    start, step, off = lp.side(which)
    img = np.ascontiguousarray(image, np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    offsets = np.arange(-neighbours, neighbours + 1) * neighbour_step * lp.phi_step
    Minv = np.ascontiguousarray(Rc @ np.linalg.inv(K))  # homogeneous pixel -> camera-1-axes ray
    M = np.ascontiguousarray(K @ Rc.T)  # and back
    return kernel(img, start, step, off, np.ascontiguousarray(lp.phi, np.float64), offsets.astype(np.float64),
                  np.ascontiguousarray(lp.basis, np.float64), Minv, M)


def sample_lines(image: np.ndarray, start: np.ndarray, step: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` along lines, flat (sum(count), C) float32.

    Args:
        image: (H, W) or (H, W, C), any dtype; sampled as float32.
    """
    from .kernels import sample_line_channels as kernel

    img = np.ascontiguousarray(image, np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    count = np.asarray(count, np.int64).reshape(-1)
    off = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
    L = len(count)
    return kernel(img, np.ascontiguousarray(start, np.float64).reshape(L, 2),
                  np.ascontiguousarray(step, np.float64).reshape(L, 2), off, np.zeros(L), np.zeros(1),
                  np.eye(3), np.eye(3), np.eye(3))
