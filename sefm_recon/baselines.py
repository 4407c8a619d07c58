"""Dense baselines for comparison: OpenCV StereoSGBM on a truly rectified pair, and
OpenCV's DIS optical flow checked forward and backward.

The pair is rectified with the rotations of ``cv2.stereoRectify`` computed from the
true relative pose; the rectified cameras keep the focal length of view 1 and get a
canvas (principal points) chosen so that the whole of both images fits and no
disparity search window leaves the canvas.  Every valid SGBM disparity is mapped
back analytically to a match in the ORIGINAL images (COLMAP pixel convention).

OpenCV pixel convention: the centre of the top-left pixel is (0, 0); COLMAP: (0.5,
0.5).  All OpenCV-side matrices below are COLMAP ``K`` shifted by -0.5 in ``cx, cy``.
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

log = logging.getLogger(__name__)

__all__ = ["sgbm_matches", "scene_depth_range", "rectify_pair", "epipoles_inside", "dis_matches",
           "DIS_AGREEMENT_PX"]

#: DIS matches are kept where the forward flow and the backward flow at its end agree
#: within this many pixels (the peer's definition in the evaluation).
DIS_AGREEMENT_PX = 1.0


def scene_depth_range(view1, view2, margin: float = 0.03) -> tuple[float, float]:
    """(zmin, zmax) of the finite ground-truth depths of both views, widened by ``margin``."""
    ds = [np.asarray(v.depth) for v in (view1, view2)]
    fin = np.concatenate([d[np.isfinite(d) & (d > 0)].ravel() for d in ds])
    if fin.size == 0:
        raise ValueError("no finite depth in either view")
    return float(fin.min()) * (1.0 - margin), float(fin.max()) * (1.0 + margin)


def _cv_K(K: np.ndarray) -> np.ndarray:
    Kc = np.array(K, np.float64, copy=True)
    Kc[0, 2] -= 0.5
    Kc[1, 2] -= 0.5
    return Kc


def rectify_pair(K1, R1, t1, K2, R2, t2, size1, size2):
    """Rectifying rotations and the relative geometry.

    Returns ``(Rr1, Rr2, B)``: ``Rr_k`` maps camera-k coordinates to the common
    rectified frame (rows parallel to the baseline), ``B`` the signed baseline such
    that rectified camera 2 sits at ``(B, 0, 0)`` in rectified camera-1 coordinates
    (``B > 0``: camera 2 is to the right of camera 1).
    """
    R1 = np.asarray(R1, np.float64)
    R2 = np.asarray(R2, np.float64)
    t1 = np.asarray(t1, np.float64).reshape(3)
    t2 = np.asarray(t2, np.float64).reshape(3)
    Rrel = R2 @ R1.T
    Trel = t2 - Rrel @ t1  # X2 = Rrel X1 + Trel
    z = np.zeros(5)
    Rr1, Rr2, _, _, _, _, _ = cv2.stereoRectify(
        _cv_K(K1), z, _cv_K(K2), z, tuple(int(s) for s in size1), Rrel, Trel.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1
    )
    Rr1 = np.asarray(Rr1, np.float64)
    Rr2 = np.asarray(Rr2, np.float64)
    T_r = Rr2 @ Trel  # X2r = X1r + T_r,  T_r = (-B, 0, 0)
    if abs(T_r[1]) + abs(T_r[2]) > 1e-6 * np.linalg.norm(T_r):
        log.warning("rectification residual: T_r = %s", T_r)
    return Rr1, Rr2, float(-T_r[0])


def _warp_bounds(Kc, Rr, W, H):
    """Rectified normalised-coordinate bounds (x0, x1, y0, y1) of an image, and its corner rays."""
    u = np.array([0, W - 1, 0, W - 1, (W - 1) / 2, (W - 1) / 2, 0, W - 1], float)
    v = np.array([0, 0, H - 1, H - 1, 0, H - 1, (H - 1) / 2, (H - 1) / 2], float)
    rays = Rr @ np.linalg.inv(Kc) @ np.vstack([u, v, np.ones_like(u)])
    x = rays[0] / rays[2]
    y = rays[1] / rays[2]
    return x.min(), x.max(), y.min(), y.max(), rays


def _to_original(Kc, Rr, f, cx, cy, x, y):
    """Rectified OpenCV pixel (x, y) -> original COLMAP pixel coordinates and validity."""
    r = np.stack([(x - cx) / f, (y - cy) / f, np.ones_like(x)])
    p = Kc @ (Rr.T @ r)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = p[0] / p[2] + 0.5
        v = p[1] / p[2] + 0.5
    return u, v, p[2] > 0


def sgbm_matches(
    img1,
    img2,
    K1,
    R1,
    t1,
    K2,
    R2,
    t2,
    disparity_range=None,
    block_size: int = 5,
    depth_range=None,
    mode: int = cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    margin_px: float = 0.0,
):
    """Dense matches from StereoSGBM on the truly rectified pair.

    ``depth_range=(zmin, zmax)`` (camera z-depth, e.g. :func:`scene_depth_range`) sets
    the disparity search range; otherwise ``disparity_range=(dmin, dmax)`` in
    rectified pixels of ``f * B / Z`` (0 = infinitely far); default ``(0, 0.3 * W)``.
    Either is widened by ``margin_px`` on each side.
    Returns ``(uv1 (N, 2), uv2 (N, 2))`` float64 COLMAP coordinates in the original
    images, one match per valid disparity pixel of the left rectified image.
    """
    img1 = np.asarray(img1)
    img2 = np.asarray(img2)
    H1, W1 = img1.shape[:2]
    H2, W2 = img2.shape[:2]
    Rr1, Rr2, B = rectify_pair(K1, R1, t1, K2, R2, t2, (W1, H1), (W2, H2))
    if B < 0:  # camera 2 is on the left: run with the roles swapped
        uv2, uv1 = sgbm_matches(
            img2, img1, K2, R2, t2, K1, R1, t1, disparity_range, block_size, depth_range, mode, margin_px
        )
        return uv1, uv2
    Kc1, Kc2 = _cv_K(K1), _cv_K(K2)
    f = float(K1[0, 0] + K1[1, 1]) / 2.0
    ax0, ax1, ay0, ay1, rays1 = _warp_bounds(Kc1, Rr1, W1, H1)
    bx0, bx1, by0, by1, rays2 = _warp_bounds(Kc2, Rr2, W2, H2)
    # common rows: only the overlap of both images can match
    y0, y1 = max(ay0, by0), min(ay1, by1)
    if y1 <= y0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    Hr = int(math.ceil(f * (y1 - y0))) + 1
    cy = -f * y0
    # disparity (content coordinates, cx_k = -f * x0_k): d = f B / Z + f (bx0 - ax0)
    dc = f * (bx0 - ax0)
    if depth_range is not None:
        zmin, zmax = float(depth_range[0]), float(depth_range[1])
        # Z in the rectified frame = z-depth * (rectified ray z / camera ray z); bound it
        zr = rays1[2]  # rectified z of camera-1 rays with camera z = 1 (linear in u, v)
        zr_min, zr_max = float(zr.min()), float(zr.max())
        zr_min, zr_max = min(zr_min, 1.0), max(zr_max, 1.0)
        d_lo = f * B / (zmax * zr_max)
        d_hi = f * B / (max(zmin, 1e-9) * zr_min)
    elif disparity_range is not None:
        d_lo, d_hi = float(disparity_range[0]), float(disparity_range[1])
    else:
        d_lo, d_hi = 0.0, 0.3 * W1
    d_lo, d_hi = d_lo - margin_px, d_hi + margin_px
    min_d = int(math.floor(d_lo + dc)) - 2
    num_d = int(math.ceil((d_hi - d_lo + 4) / 16.0)) * 16
    max_d = min_d + num_d
    # canvas: shift both images by ox so every left pixel has its whole search window
    ox = max(max_d, 0) + 1
    cx1 = -f * ax0 + ox
    cx2 = -f * bx0 + ox
    Wr = int(max(cx1 + f * ax1, cx2 + f * bx1)) + 2 + max(-min_d, 0)
    P1 = np.array([[f, 0, cx1], [0, f, cy], [0, 0, 1.0]])
    P2 = np.array([[f, 0, cx2], [0, f, cy], [0, 0, 1.0]])
    m1x, m1y = cv2.initUndistortRectifyMap(Kc1, None, Rr1, P1, (Wr, Hr), cv2.CV_32FC1)
    m2x, m2y = cv2.initUndistortRectifyMap(Kc2, None, Rr2, P2, (Wr, Hr), cv2.CV_32FC1)
    rect1 = cv2.remap(img1, m1x, m1y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    rect2 = cv2.remap(img2, m2x, m2y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    cn = 1 if rect1.ndim == 2 else rect1.shape[2]
    sgbm = cv2.StereoSGBM_create(
        minDisparity=min_d,
        numDisparities=num_d,
        blockSize=block_size,
        P1=8 * cn * block_size**2,
        P2=32 * cn * block_size**2,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=mode,
    )
    log.debug("SGBM: rectified %dx%d, disparities [%d, %d)", Wr, Hr, min_d, max_d)
    disp = sgbm.compute(rect1, rect2).astype(np.float32) / 16.0
    # valid: a disparity inside the search range, on pixels covered by both images
    valid = disp >= min_d
    ii, jj = np.nonzero(valid)
    d = disp[ii, jj].astype(np.float64)
    x1 = jj.astype(np.float64)
    y = ii.astype(np.float64)
    x2 = x1 - d
    u1, v1, ok1 = _to_original(Kc1, Rr1, f, cx1, cy, x1, y)
    u2, v2, ok2 = _to_original(Kc2, Rr2, f, cx2, cy, x2, y)
    ok = ok1 & ok2
    ok &= (u1 >= 0) & (u1 < W1) & (v1 >= 0) & (v1 < H1)
    ok &= (u2 >= 0) & (u2 < W2) & (v2 >= 0) & (v2 < H2)
    return np.column_stack([u1[ok], v1[ok]]), np.column_stack([u2[ok], v2[ok]])


def epipoles_inside(K1, R1, t1, K2, R2, t2, size1, size2) -> bool:
    """Whether either epipole lies inside its image: no planar rectification exists then."""
    from .geometry.epipolar import epipoles

    R1, R2 = np.asarray(R1, np.float64), np.asarray(R2, np.float64)
    R = R2 @ R1.T  # cam2_from_cam1
    t = np.asarray(t2, np.float64).reshape(3) - R @ np.asarray(t1, np.float64).reshape(3)
    for p, (w, h) in zip(epipoles(np.asarray(K1, np.float64), np.asarray(K2, np.float64), R, t), (size1, size2)):
        if abs(p[2]) > 1e-12 * np.linalg.norm(p):
            u, v = p[:2] / p[2]
            if 0 <= u < w and 0 <= v < h:
                return True
    return False


def dis_matches(img1, img2, agreement_px: float = DIS_AGREEMENT_PX):
    """Dense matches from OpenCV DIS optical flow (PRESET_MEDIUM, grey images).

    The flow is computed forward and backward; a pixel of image 1 is kept where
    the backward flow at the end of its forward flow brings it back within
    ``agreement_px`` and the end lies inside image 2. Images of different sizes are
    padded to a common canvas at the top left (their coordinates do not change).
    Returns ``(uv1 (N, 2), uv2 (N, 2))`` float64 COLMAP coordinates.
    """
    g1 = cv2.cvtColor(np.asarray(img1), cv2.COLOR_RGB2GRAY)
    g2 = cv2.cvtColor(np.asarray(img2), cv2.COLOR_RGB2GRAY)
    (h1, w1), (h2, w2) = g1.shape, g2.shape
    H, W = max(h1, h2), max(w1, w2)
    c1 = np.zeros((H, W), np.uint8)
    c2 = np.zeros((H, W), np.uint8)
    c1[:h1, :w1] = g1
    c2[:h2, :w2] = g2
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fwd = dis.calc(c1, c2, None)
    bwd = dis.calc(c2, c1, None)
    jj, ii = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    x2 = jj + fwd[..., 0]
    y2 = ii + fwd[..., 1]
    back = cv2.remap(bwd, x2, y2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(np.nan, np.nan))
    with np.errstate(invalid="ignore"):
        err = np.hypot(fwd[..., 0] + back[..., 0], fwd[..., 1] + back[..., 1])
        keep = (err <= agreement_px) & (x2 >= -0.5) & (x2 < w2 - 0.5) & (y2 >= -0.5) & (y2 < h2 - 0.5)
    keep[h1:, :] = False
    keep[:, w1:] = False
    ii, jj = np.nonzero(keep)
    uv1 = np.column_stack([jj + 0.5, ii + 0.5]).astype(np.float64)
    uv2 = np.column_stack([x2[ii, jj] + 0.5, y2[ii, jj] + 0.5]).astype(np.float64)
    return uv1, uv2
