"""Two-view triangulation of matches with a known relative pose (vectorised)."""

from __future__ import annotations

import numpy as np


def triangulate(K1, K2, R, t, uv1, uv2):
    """Midpoint triangulation of matches in camera 1's frame.

    Camera 1 is at the origin with identity rotation, camera 2 at
    ``x_cam2 = R @ X + t``. Each point is the midpoint of the shortest segment
    between the two viewing rays.

    Returns:
        X (N, 3) points; valid (N,) bool: finite, in front of both cameras.
        angle (N,) triangulation angle, radians.
    """
    from .kernels import triangulate_midpoint

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
