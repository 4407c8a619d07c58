"""The working frame: a downscaled, undistorted pinhole version of each photo.

Matching runs on pinhole images no larger than ``max_size``; matches are mapped
back to the original photo's pixels (with its distortion) at the end, so every
coordinate the user sees refers to the input image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

from ..io.cameras import has_distortion


@dataclass
class WorkingView:
    image: np.ndarray  #: (h, w, 3) uint8, undistorted and scaled
    K: np.ndarray  #: (3, 3) pinhole matrix of ``image``
    camera: pycolmap.Camera  #: the original camera (original resolution, with distortion)
    scale: float  #: working size / original size

    @property
    def size(self) -> tuple[int, int]:
        return self.image.shape[1], self.image.shape[0]

    def to_original(self, uv: np.ndarray) -> np.ndarray:
        """Working pixel coordinates -> original image pixel coordinates, (N, 2) float64.

        Where the working image is the photo (scale 1, no distortion) ``uv`` itself is
        returned (as float64): the same pixels, and copying 2.6 M matches twice cost 0.09 s.
        """
        if len(uv) == 0:
            return np.zeros((0, 2))
        uv = np.asarray(uv, dtype=np.float64)
        if not has_distortion(self.camera):
            if self.scale == 1.0:
                return uv
            # A pinhole camera maps affinely; pycolmap's per-point call costs 0.1 s per million.
            A = pinhole_matrix(self.camera) @ np.linalg.inv(self.K)
            return uv @ np.ascontiguousarray(A[:2, :2].T) + A[:2, 2]  # (a strided operand: 3 x the time)
        rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(self.K).T
        return np.asarray(self.camera.img_from_cam(np.ascontiguousarray(rays)), dtype=np.float64)


def pinhole_matrix(camera: pycolmap.Camera, scale: float = 1.0) -> np.ndarray:
    """K of the camera's pinhole part, scaled (COLMAP convention: pixel edges scale exactly)."""
    K = np.asarray(camera.calibration_matrix(), dtype=np.float64).copy()
    K[:2] *= scale
    return K


def make_working_view(image: np.ndarray, camera: pycolmap.Camera, max_size: int = 0) -> WorkingView:
    """Downscale to at most ``max_size`` px (longest side) and remove lens distortion."""
    h, w = image.shape[:2]
    scale = 1.0
    if max_size and max(w, h) > max_size:
        scale = max_size / max(w, h)
    ws, hs = max(1, round(w * scale)), max(1, round(h * scale))
    # Use the exact ratio per axis is not needed: round() changes it by < 1/size.
    K = pinhole_matrix(camera, ws / w)
    if not has_distortion(camera):
        work = cv2.resize(image, (ws, hs), interpolation=cv2.INTER_AREA) if scale < 1.0 else image
        return WorkingView(np.ascontiguousarray(work), K, camera, ws / w)
    small = cv2.resize(image, (ws, hs), interpolation=cv2.INTER_AREA) if scale < 1.0 else image
    # For every working pixel centre: ray through K, then the distorted camera's
    # pixel, rescaled into the downscaled image; OpenCV centres are at integers.
    jj, ii = np.meshgrid(np.arange(ws) + 0.5, np.arange(hs) + 0.5)
    uv = np.c_[jj.ravel(), ii.ravel()]
    rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T
    src = np.asarray(camera.img_from_cam(np.ascontiguousarray(rays)), dtype=np.float64) * (ws / w)
    mapx = (src[:, 0] - 0.5).reshape(hs, ws).astype(np.float32)
    mapy = (src[:, 1] - 0.5).reshape(hs, ws).astype(np.float32)
    work = cv2.remap(small, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return WorkingView(work, K, camera, ws / w)
