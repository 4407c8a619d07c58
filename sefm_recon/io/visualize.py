"""Pictures for people: match overlays, point-cloud renders, PNG/JPEG writing.

All images are (H, W, 3) uint8 RGB; pixel coordinates follow COLMAP (centre of
the top-left pixel is (0.5, 0.5)). OpenCV drawing uses centre-at-(0, 0), so
0.5 is subtracted before drawing.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np
from numba import njit

from sefm_recon.arrays import finite_rows
from sefm_recon.io.ply import atomic_path

log = logging.getLogger(__name__)

__all__ = ["draw_matches", "render_points", "write_image"]

_SHIFT = 4  # fractional bits for sub-pixel cv2 drawing


def _as_rgb_u8(img: np.ndarray) -> np.ndarray:
    """(H, W), (H, W, 1), (H, W, 3) or (H, W, 4), uint8 or float in [0, 1] -> (H, W, 3) uint8."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating):
            img = np.clip(np.nan_to_num(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        else:
            img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3:
        raise ValueError(f"image must be (H, W) or (H, W, C), got {img.shape}")
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    elif img.shape[2] != 3:
        raise ValueError(f"image must have 1, 3 or 4 channels, got {img.shape}")
    return np.ascontiguousarray(img)


def _resize(img: np.ndarray, s: float) -> np.ndarray:
    if s == 1.0:
        return img.copy()
    h, w = img.shape[:2]
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)


@njit(cache=True, nogil=True)
def _pixel_counts(uv, ok, sx, sy, h, w):
    """Matches per pixel of an (h, w) picture: ``uv`` (N, 2) COLMAP coordinates scaled by
    (sx, sy), rows where ``ok`` is False skipped, positions clamped to the picture.
    One pass over millions of matches instead of five array operations on them; without
    Python's lock, as the picture is drawn beside the COLMAP model's Python loop."""
    out = np.zeros((h, w), np.float32)
    for k in range(uv.shape[0]):
        if ok[k]:
            c = min(max(int(np.floor(uv[k, 0] * sx)), 0), w - 1)
            r = min(max(int(np.floor(uv[k, 1] * sy)), 0), h - 1)
            out[r, c] += 1.0
    return out


def _density_shade(img: np.ndarray, counts: np.ndarray, floor: float = 0.4) -> np.ndarray:
    """Dim ``img`` where matches are sparse: brightness ``floor`` with no matches,
    full brightness where the smoothed match density reaches its 90th percentile.

    ``counts``: (H, W) matches per pixel of ``img`` (:func:`_pixel_counts`).
    """
    h, w = img.shape[:2]
    if not counts.any():
        return (img.astype(np.float32) * floor + 0.5).astype(np.uint8)
    dens = cv2.GaussianBlur(counts, (0, 0), max(1.5, 0.006 * max(h, w)))
    pos = dens[dens > 1e-6]
    top = float(np.percentile(pos, 90)) if len(pos) else 1.0
    gain = floor + (1.0 - floor) * np.clip(dens / max(top, 1e-12), 0, 1)
    return np.clip(img.astype(np.float32) * gain[:, :, None] + 0.5, 0, 255).astype(np.uint8)


def draw_matches(
    img1: np.ndarray,
    img2: np.ndarray,
    uv1: np.ndarray,
    uv2: np.ndarray,
    max_lines: int = 300,
    seed: int = 0,
    max_width: int = 2000,
) -> np.ndarray:
    """Side-by-side match picture.

    Image 1 on the left, image 2 on the right (top-aligned, black padding),
    both scaled by the same factor so the output is at most ``max_width`` wide.
    Both images are dimmed (to 40 % brightness) where there are no matches and
    kept at full brightness where matches are dense, so coverage is visible at
    a glance; a random subset of ``max_lines`` matches is drawn
    as lines coloured by the y of the point in image 1 (hue: red at the top
    through blue at the bottom), with a dot at each end.

    Args:
        img1, img2: (H1, W1, 3) / (H2, W2, 3) uint8 RGB (grey/float accepted).
        uv1, uv2: (N, 2) COLMAP pixel coordinates of the matches.
        max_lines: number of lines to draw (random subset, ``seed``).

    Returns:
        (H, W, 3) uint8 RGB with ``W = round(s*W1) + round(s*W2)``,
        ``H = max(round(s*H1), round(s*H2))``, ``s = min(1, max_width/(W1+W2))``.
    """
    a = _as_rgb_u8(img1)
    b = _as_rgb_u8(img2)
    uv1 = np.asarray(uv1, dtype=np.float64).reshape(-1, 2)
    uv2 = np.asarray(uv2, dtype=np.float64).reshape(-1, 2)
    if len(uv1) != len(uv2):
        raise ValueError(f"uv1 and uv2 differ in length: {len(uv1)} vs {len(uv2)}")
    ok = finite_rows(uv1, uv2)

    s = min(1.0, max_width / float(a.shape[1] + b.shape[1]))
    a, b = _resize(a, s), _resize(b, s)
    # COLMAP coordinates scale exactly with the image (pixel edges at 0 and W)
    sx1, sy1 = a.shape[1] / img1.shape[1], a.shape[0] / img1.shape[0]
    sx2, sy2 = b.shape[1] / img2.shape[1], b.shape[0] / img2.shape[0]
    a = _density_shade(a, _pixel_counts(uv1, ok, sx1, sy1, *a.shape[:2]))
    b = _density_shade(b, _pixel_counts(uv2, ok, sx2, sy2, *b.shape[:2]))
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1]:] = b

    good = np.flatnonzero(ok)
    n = len(good)
    if n and max_lines > 0:
        rng = np.random.default_rng(seed)
        sel = good[rng.choice(n, size=min(n, int(max_lines)), replace=False)]
        p1, p2 = uv1[sel] * (sx1, sy1), uv2[sel] * (sx2, sy2)
        hue = np.clip(p1[:, 1] / max(a.shape[0], 1), 0, 1) * 150  # OpenCV hue 0..180
        hsv = np.stack([hue, np.full_like(hue, 255), np.full_like(hue, 255)], -1)
        colors = cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0]
        q1 = np.rint((p1 - 0.5) * (1 << _SHIFT)).astype(np.int64)
        q2 = np.rint((p2 - 0.5 + (a.shape[1], 0)) * (1 << _SHIFT)).astype(np.int64)
        thick = max(1, round(h / 800))
        r = (thick + 1) << _SHIFT
        for c, e1, e2 in zip(colors.tolist(), q1.tolist(), q2.tolist()):
            cv2.line(canvas, e1, e2, c, thick, cv2.LINE_AA, _SHIFT)
            cv2.circle(canvas, e1, r, c, -1, cv2.LINE_AA, _SHIFT)
            cv2.circle(canvas, e2, r, c, -1, cv2.LINE_AA, _SHIFT)
    return canvas


def render_points(
    xyz: np.ndarray,
    rgb: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    width: int,
    height: int,
    point_size: int = 1,
) -> np.ndarray:
    """Splat a coloured point cloud into a pinhole view, z-buffered.

    A point projects to ``uv = dehom(K @ (R @ X + t))`` (COLMAP pixels) and
    lands in pixel ``(row, col) = (floor(v), floor(u))``; with ``point_size``
    p > 1 it covers the p x p block of pixels around that one (offsets
    ``-(p-1)//2 .. p//2``). Points with z <= 0 are ignored. Where several
    points cover a pixel the nearest (smallest z) wins. Background is black.

    Args:
        xyz: (N, 3) world points. rgb: (N, 3) uint8.
        K: (3, 3) intrinsics. R (3, 3), t (3,): cam_from_world.
        width, height: output size in pixels.

    Returns:
        (height, width, 3) uint8 RGB.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb)
    if rgb.shape != xyz.shape:
        raise ValueError(f"rgb must be {xyz.shape}, got {rgb.shape}")
    K = np.asarray(K, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    out = np.zeros((int(height), int(width), 3), np.uint8)
    if len(xyz) == 0:
        return out

    xc = xyz @ R.T + t
    z = xc[:, 2]
    front = np.isfinite(xc).all(1) & (z > 0)
    xc, z, col_rgb = xc[front], z[front], rgb[front]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = xc @ K.T
        u = proj[:, 0] / proj[:, 2]
        v = proj[:, 1] / proj[:, 2]
    good = np.isfinite(u) & np.isfinite(v)
    # avoid int overflow for points far outside the view
    good &= (u > -point_size - 1) & (u < width + point_size + 1)
    good &= (v > -point_size - 1) & (v < height + point_size + 1)
    col = np.floor(u[good]).astype(np.int64)
    row = np.floor(v[good]).astype(np.int64)
    z, col_rgb = z[good], col_rgb[good]

    p = max(1, int(point_size))
    if p > 1:
        offs = np.arange(-((p - 1) // 2), p // 2 + 1)  # p offsets: -(p-1)//2 .. p//2
        dy, dx = np.meshgrid(offs, offs, indexing="ij")
        row = (row[:, None] + dy.ravel()).ravel()
        col = (col[:, None] + dx.ravel()).ravel()
        z = np.repeat(z, p * p)
        col_rgb = np.repeat(col_rgb, p * p, axis=0)
    inside = (row >= 0) & (row < height) & (col >= 0) & (col < width)
    if not inside.any():
        return out
    pix = row[inside] * int(width) + col[inside]
    z, col_rgb = z[inside], col_rgb[inside]
    order = np.lexsort((z, pix))  # by pixel, then nearest first
    pix_sorted = pix[order]
    first = np.ones(len(order), bool)
    first[1:] = pix_sorted[1:] != pix_sorted[:-1]
    win = order[first]
    out.reshape(-1, 3)[pix[win]] = col_rgb[win]
    return out


def write_image(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an RGB (or grey) image atomically (temp file + ``os.replace``).

    The format follows ``path``'s extension (``.png``, ``.jpg``, ...). RGB is
    converted to OpenCV's BGR. Returns ``Path(path)``; raises ``OSError`` if
    OpenCV cannot encode it or the file cannot be written. The image is encoded
    in memory and written by Python: ``cv2.imwrite`` crashes on a path with
    bytes that are not UTF-8.
    """
    path = Path(path)
    img = np.asarray(rgb)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGBA2BGRA)
    elif img.ndim != 2:
        raise ValueError(f"image must be (H, W), (H, W, 3) or (H, W, 4), got {img.shape}")
    ok, buf = cv2.imencode(path.suffix or ".png", img)
    if not ok:
        raise OSError(f"OpenCV cannot encode {path.name}")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(buf.tobytes())
    log.debug("wrote %s", path)
    return path
