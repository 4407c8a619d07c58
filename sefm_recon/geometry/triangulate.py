"""Two-view triangulation of matches with a known relative pose (vectorised)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .epipolar import pixel_ray


def triangulate(K1, K2, R, t, uv1, uv2):
    """Midpoint triangulation of matches in camera 1's frame.

    Camera 1 is at the origin with identity rotation, camera 2 at
    ``x_cam2 = R @ X + t``. Each point is the midpoint of the shortest segment
    between the two viewing rays.

    Returns:
        X (N, 3) points; valid (N,) bool: finite, in front of both cameras.
        angle (N,) triangulation angle, radians.
    """
    uv1 = np.ascontiguousarray(uv1, np.float64).reshape(-1, 2)
    uv2 = np.ascontiguousarray(uv2, np.float64).reshape(-1, 2)
    R = np.asarray(R, np.float64)
    c2 = -R.T @ np.asarray(t, np.float64).reshape(3)
    X = np.empty((len(uv1), 3))
    valid, angle = triangulate_midpoint(np.linalg.inv(K1), np.linalg.inv(K2), np.ascontiguousarray(R.T), c2, uv1, uv2, X)
    return X, valid, angle


def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of points X (N, 3) in a camera ``x_cam = R X + t``."""
    x = (X @ R.T + t) @ K.T
    return x[:, :2] / x[:, 2:3]


def reprojection_errors(K1, K2, R, t, uv1, uv2, X) -> np.ndarray:
    """Mean of both images' reprojection errors, pixels, (N,)."""
    e1 = np.linalg.norm(project(K1, np.eye(3), np.zeros(3), X) - uv1, axis=1)
    e2 = np.linalg.norm(project(K2, R, t, X) - uv2, axis=1)
    return 0.5 * (e1 + e2)


# ------------------------------------------------------------------ numba kernels


class Midpoint(NamedTuple):
    """Midpoint of the shortest segment between two viewing rays (:func:`ray_midpoint`)."""

    x: float  #: the point, camera-1 frame
    y: float
    z: float
    s1: float  #: distance along ray 1 (unit length) to its closest point; NaN for parallel rays
    s2: float  #: the same along ray 2
    cos: float  #: cosine of the angle between the rays


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
