"""Reading photos: any format OpenCV decodes, EXIF orientation applied, 8 or 16 bit."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError

#: Images with a shorter side below this many pixels are refused: too few
#: epipolar lines and SIFT features to estimate geometry.
MIN_SIZE = 64


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as (H, W, 3) uint8 RGB; grey images are replicated to 3 channels.

    EXIF orientation is honoured (OpenCV rotates on decode); 16-bit images are
    scaled to 8 bit. Raises :class:`InputError` for a missing, empty,
    undecodable or too small file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"image not found: {path}")
    if path.stat().st_size == 0:
        raise InputError(f"image is empty (0 bytes): {path}")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    if img is None or img.size == 0:
        raise InputError(f"cannot decode image (not a PNG/JPEG/TIFF/... file?): {path}")
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    h, w = img.shape[:2]
    if min(h, w) < MIN_SIZE:
        raise InputError(f"image too small to match: {w}x{h} px, need at least {MIN_SIZE} px on each side: {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey of an RGB image."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
