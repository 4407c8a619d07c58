"""Real rectified stereo pairs with dense ground truth, and their exactly known variants.

A real pair (Middlebury 2001 / 2006, loaded by :mod:`sefm_recon.io.real_gt`) comes with
the disparity of image 1 and its occlusions. Any focal length is consistent with a
rectified pair; we take ``f = 1.2 * max(W, H)``, the principal point at the image
centre, camera 1 at the origin and camera 2 at ``t = (-1, 0, 0)`` (COLMAP:
``x_cam = R @ X + t``, unit baseline), so ``depth = f / disparity``.

Variants with exact ground truth turn a camera about its centre by a known rotation
``R_w`` and warp its image with the homography ``K @ R_w @ K^-1`` onto the warped
image's bounding box (that shift goes into the new camera's principal point):

* ``rect``: as published;
* ``unrect``: camera 2 turned by :data:`UNRECT_ROTVEC_DEG` (about 13 deg, about x, y and z);
* ``conv``: camera 1 turned by ``-CONV_ROTVEC_DEG`` and camera 2 by ``+CONV_ROTVEC_DEG``,
  towards each other (about 14 deg between them).

The true match of a COLMAP position ``uv1'`` of (warped) image 1 is found by undoing
image 1's warp, reading the disparity there, stepping ``d`` px to the left and
applying image 2's warp. Pixel conventions are those of ``docs/CONVENTIONS.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "FOCAL_FACTOR",
    "UNRECT_ROTVEC_DEG",
    "CONV_ROTVEC_DEG",
    "VARIANTS",
    "RealPair",
    "StereoCase",
    "lr_occlusion",
    "make_case",
    "rotation",
    "turn_angle_deg",
    "calibration",
]

#: f = FOCAL_FACTOR * max(W, H): a normal lens (about 45 deg across the long side).
FOCAL_FACTOR = 1.2
#: Camera 2's turn in ``unrect`` (rotation vector, degrees; |v| = 13.0 deg): mixed about
#: x, y and z so that neither the rows nor the columns stay aligned.
UNRECT_ROTVEC_DEG = (4.0, 11.5, 4.5)
#: Camera 2's turn in ``conv``; camera 1 turns by its opposite (degrees; |v| = 7.0 deg, 14
#: deg between them): mostly about y, so that the optical axes turn towards each other
#: (camera 2 sits at +x), plus some x and z.
CONV_ROTVEC_DEG = (1.5, 6.5, -2.0)
VARIANTS = ("rect", "unrect", "conv")
#: A 2x2 disparity neighbourhood wider than this (px) spans a depth edge: read the
#: nearest pixel there instead of interpolating across the edge.
EDGE_DISPARITY_PX = 1.0
#: Left-right check tolerance (px): the data's README defines occlusion with it.
LR_TOLERANCE_PX = 1.0


@dataclass
class RealPair:
    """A rectified pair as published: ``disp`` (H, W) float64 px of image 1, NaN = unknown;
    ``occluded`` (H, W) bool: known disparity, but the point is hidden in image 2."""

    name: str
    img1: np.ndarray  # (H, W, 3) uint8 RGB
    img2: np.ndarray  # (H, W, 3) uint8 RGB
    disp: np.ndarray
    occluded: np.ndarray


def lr_occlusion(disp1: np.ndarray, disp2: np.ndarray, tol: float = LR_TOLERANCE_PX) -> np.ndarray:
    """Pixels of image 1 hidden in image 2: left-right check of ``disp1`` against ``disp2``.

    Both (H, W) float px (NaN = unknown); the match of pixel ``(x, y)`` is ``(x - d, y)``.
    A pixel with a known disparity is occluded where the disparity of image 2 at its
    match (nearest pixel) differs by more than ``tol`` or is unknown; a match outside
    image 2 is occluded too.
    """
    H, W = disp1.shape
    jj = np.broadcast_to(np.arange(W, dtype=np.float64), (H, W))
    ii = np.broadcast_to(np.arange(H)[:, None], (H, W))
    with np.errstate(invalid="ignore"):
        x2 = np.rint(jj - disp1)
        inside = (x2 >= 0) & (x2 < W)
    x2i = np.where(inside, x2, 0).astype(np.int64)
    d2 = disp2[ii, x2i]
    with np.errstate(invalid="ignore"):
        agree = inside & (np.abs(d2 - disp1) <= tol)
    return np.isfinite(disp1) & ~agree


def rotation(rotvec_deg) -> np.ndarray:
    """3x3 rotation matrix of a rotation vector in degrees."""
    R, _ = cv2.Rodrigues(np.radians(np.asarray(rotvec_deg, np.float64)).reshape(3, 1))
    return R


def _shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def _apply(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = np.column_stack([uv, np.ones(len(uv))]) @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


def _turn(img: np.ndarray, K: np.ndarray, R_w: np.ndarray):
    """Warp ``img`` as seen by its camera turned by ``R_w``; returns (image, K', H).

    ``H`` maps COLMAP positions of ``img`` to those of the new image; ``K'`` is the
    turned camera's calibration (its principal point moved with the bounding box).
    """
    h, w = img.shape[:2]
    Hk = K @ R_w @ np.linalg.inv(K)
    corners = _apply(Hk, np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]))
    x0, y0 = np.floor(corners.min(axis=0))
    x1, y1 = np.ceil(corners.max(axis=0))
    H = _shift(-x0, -y0) @ Hk
    size = (int(x1 - x0), int(y1 - y0))
    # OpenCV puts pixel centres at integers: conjugate with the half-pixel shift
    H_cv = _shift(-0.5, -0.5) @ H @ _shift(0.5, 0.5)
    out = cv2.warpPerspective(img, H_cv, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return out, _shift(-x0, -y0) @ K, H


@dataclass
class StereoCase:
    """One pair in one variant: images, true cameras and the ground truth of every match.

    ``H1``/``H2`` (3x3) map COLMAP positions of the published images to those of
    ``img1``/``img2``; the poses are cam_from_world with world = camera 1 as published.
    """

    name: str
    variant: str
    img1: np.ndarray
    img2: np.ndarray
    K1: np.ndarray
    R1: np.ndarray
    t1: np.ndarray
    K2: np.ndarray
    R2: np.ndarray
    t2: np.ndarray
    H1: np.ndarray
    H2: np.ndarray
    pair: RealPair

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) cam2_from_cam1."""
        R = self.R2 @ self.R1.T
        return R, self.t2 - R @ self.t1

    def _published(self, uv1: np.ndarray):
        """Positions in the published image 1, and whether they lie inside it."""
        uv = _apply(np.linalg.inv(self.H1), np.asarray(uv1, np.float64).reshape(-1, 2))
        H, W = self.pair.disp.shape
        with np.errstate(invalid="ignore"):
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        return np.where(inside[:, None], uv, 0.5), inside

    def truth(self, uv1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True positions in ``img2`` of COLMAP positions ``uv1`` (N, 2) of ``img1``.

        Returns ``(uv2 (N, 2), covisible (N,) bool)``: the disparity is interpolated
        bilinearly between the four surrounding pixel centres, or read at the pixel
        holding ``uv1`` where they span a depth edge or an unknown value; a position is
        co-visible when it lies inside the published image 1 on a pixel whose
        disparity is known and not occluded.
        """
        from .evaluate import pixel_index
        from .reconstruct.points import bilinear_corners

        uv, inside = self._published(uv1)
        disp = self.pair.disp
        H, W = disp.shape
        i0, i1, j0, j1, fx, fy = bilinear_corners(H, W, uv)
        q = np.stack([disp[i0, j0], disp[i0, j1], disp[i1, j0], disp[i1, j1]])
        bil = (q[0] * (1 - fx) + q[1] * fx) * (1 - fy) + (q[2] * (1 - fx) + q[3] * fx) * fy
        ci, cj = pixel_index(uv, disp.shape)
        with np.errstate(invalid="ignore"):
            smooth = np.isfinite(q).all(axis=0) & (q.max(axis=0) - q.min(axis=0) <= EDGE_DISPARITY_PX)
        d = np.where(smooth, bil, disp[ci, cj])
        cov = inside & np.isfinite(d) & ~self.pair.occluded[ci, cj]
        uv2 = _apply(self.H2, uv - np.column_stack([d, np.zeros_like(d)]))
        uv2[~cov] = np.nan
        return uv2, cov

    def _centres(self) -> np.ndarray:
        h, w = self.img1.shape[:2]
        ii, jj = np.mgrid[0:h, 0:w]
        return np.column_stack([jj.ravel() + 0.5, ii.ravel() + 0.5])

    def covisible(self) -> np.ndarray:
        """(H, W) bool: pixel centres of ``img1`` that are co-visible in ``img2``."""
        return self.truth(self._centres())[1].reshape(self.img1.shape[:2])

    def judged(self) -> np.ndarray:
        """(H, W) bool: pixels of ``img1`` whose matches can be judged: outside the
        published image 1 (nothing there to match), or on a known disparity."""
        from .evaluate import pixel_index

        uv, inside = self._published(self._centres())
        known = np.isfinite(self.pair.disp[pixel_index(uv, self.pair.disp.shape)])
        return (~inside | known).reshape(self.img1.shape[:2])

    def depth_range(self) -> tuple[float, float]:
        """(zmin, zmax) camera z-depth of the co-visible ground-truth points in either camera."""
        disp, vis = self.pair.disp, ~self.pair.occluded & np.isfinite(self.pair.disp)
        ii, jj = np.nonzero(vis & (disp > 0))
        if ii.size == 0:
            raise ValueError(f"{self.name}: no known disparity")
        z = self.K1_published[0, 0] / disp[ii, jj]
        X = np.column_stack([jj + 0.5, ii + 0.5, np.ones(ii.size)]) @ np.linalg.inv(self.K1_published).T * z[:, None]
        zs = np.concatenate([(X @ self.R1.T + self.t1)[:, 2], (X @ self.R2.T + self.t2)[:, 2]])
        return float(zs.min()), float(zs.max())

    @property
    def K1_published(self) -> np.ndarray:
        return calibration(*self.pair.disp.shape[::-1])


def calibration(width: int, height: int) -> np.ndarray:
    """K of a published pair: f = FOCAL_FACTOR * max(W, H), principal point at the centre."""
    f = FOCAL_FACTOR * max(width, height)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def make_case(pair: RealPair, variant: str) -> StereoCase:
    """The pair in one of :data:`VARIANTS`, with its true cameras and warps."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}: one of {', '.join(VARIANTS)}")
    h, w = pair.disp.shape
    K = calibration(w, h)
    I3 = np.eye(3)
    R1, R2 = I3, I3
    if variant == "unrect":
        R2 = rotation(UNRECT_ROTVEC_DEG)
    elif variant == "conv":
        R1, R2 = rotation(-np.asarray(CONV_ROTVEC_DEG)), rotation(CONV_ROTVEC_DEG)
    img1, K1, H1 = (pair.img1, K, I3) if variant != "conv" else _turn(pair.img1, K, R1)
    img2, K2, H2 = (pair.img2, K, I3) if variant == "rect" else _turn(pair.img2, K, R2)
    t2 = R2 @ np.array([-1.0, 0.0, 0.0])  # turned about its centre: C2 = (1, 0, 0) stays
    return StereoCase(pair.name, variant, img1, img2, K1, R1, np.zeros(3), K2, R2, t2, H1, H2, pair)


def turn_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1, 1))))
