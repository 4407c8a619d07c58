"""Reading photos: any format OpenCV decodes, EXIF orientation applied, 8 or 16 bit."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from .space import captured_stderr

logger = logging.getLogger(__name__)

#: Images with a shorter side below this many pixels are refused: too few
#: epipolar lines and SIFT features to estimate geometry.
MIN_SIZE = 64

#: Largest image accepted, in pixels (OpenCV's own decoding limit is 2^30).
MAX_PIXELS = 300_000_000

#: An "edge" pixel changes by more than this many 8-bit levels per pixel
#: (central difference ``|I(x+1) - I(x-1)| / 2`` after a light blur, the
#: default SeFM key point threshold).
EDGE_LEVEL = 4.0
#: Images where fewer than this share of pixels are edge pixels are refused as
#: textureless. The weakest real photos we tried (blurred ScanNet frames) have
#: 3 % or more; a flat or smoothly shaded image has 0 %.
MIN_EDGE_SHARE = 0.005

def _decode(data: np.ndarray, flags: int) -> tuple[np.ndarray | None, str]:
    """``cv2.imdecode`` with the C library's stderr chatter captured.

    libjpeg prints "Corrupt JPEG data ..." and OpenCV "[ERROR] ... can't read
    data" straight to file descriptor 2; the user should see one line, so the
    text is captured and returned (and logged by the caller).
    """
    with captured_stderr() as chatter:
        try:
            img, err_text = cv2.imdecode(data, flags), ""
        except cv2.error as err:
            img, err_text = None, str(err)
    return img, " ".join((" ".join(chatter) + " " + err_text).split())


def header_size(data: np.ndarray) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header without decoding; None for other formats."""
    b = data[: 1 << 20].tobytes()  # EXIF, ICC and thumbnails may come before a JPEG's frame header
    if b[:8] == b"\x89PNG\r\n\x1a\n" and len(b) >= 24 and b[12:16] == b"IHDR":
        return int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")
    if b[:2] == b"\xff\xd8":
        i = 2
        while i + 4 <= len(b):
            if b[i] != 0xFF:
                return None
            marker = b[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0x01, *range(0xD0, 0xD8)):
                i += 2
                continue
            seg = int.from_bytes(b[i + 2:i + 4], "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and i + 9 <= len(b):
                return int.from_bytes(b[i + 7:i + 9], "big"), int.from_bytes(b[i + 5:i + 7], "big")
            if marker == 0xDA:
                return None
            i += 2 + seg
    return None


def _to_uint8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    f = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    lo, hi = float(f.min()), float(f.max())
    if lo >= 0.0 and hi <= 1.0:  # the usual range of float images
        return (f * 255.0 + 0.5).astype(np.uint8)
    return cv2.normalize(f, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as (H, W, 3) uint8 RGB; grey images are replicated to 3 channels.

    EXIF orientation is honoured (OpenCV rotates on decode); 16-bit images are
    scaled to 8 bit, float images from [0, 1] (else their own range); an alpha
    channel is dropped. Raises :class:`InputError` for a missing, empty,
    undecodable, too small or too large file.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"image path is a folder, not an image file: {path}")
    if not path.is_file():
        raise InputError(f"image not found: {path}")
    try:
        if path.stat().st_size == 0:
            raise InputError(f"image is empty (0 bytes): {path}")
        data = np.fromfile(str(path), dtype=np.uint8)
    except PermissionError:
        raise InputError(f"image cannot be read (permission denied): {path}") from None
    except OSError as err:
        raise InputError(f"image cannot be read ({err.strerror or err}): {path}") from None
    size = header_size(data)
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise InputError(f"image too large: {size[0]}x{size[1]} px, at most {MAX_PIXELS // 1_000_000} megapixels: "
                         f"{path}")
    # IMREAD_COLOR applies the EXIF orientation; ANYDEPTH keeps 16-bit and float data.
    img, chatter = _decode(data, cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    if img is None:
        # Some files (a one-channel float TIFF) only decode unchanged (no EXIF rotation then).
        img, chatter2 = _decode(data, cv2.IMREAD_UNCHANGED)
        chatter = chatter2 if img is not None else chatter
    if chatter:
        logger.warning("%s: the decoder reported: %s", path.name, chatter[:300])
    if img is None or img.size == 0:
        if "CV_IO_MAX_IMAGE_PIXELS" in chatter:
            raise InputError(f"image too large to decode (over {(1 << 30) // 1_000_000} megapixels): {path}")
        raise InputError(f"cannot decode image (not a PNG/JPEG/TIFF/... file, or truncated?): {path}")
    img = _to_uint8(img)
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    elif img.ndim == 3 and img.shape[2] == 2:  # grey + alpha
        img = img[:, :, 0]
    if img.ndim == 2 or img.shape[2] == 1:
        img = cv2.cvtColor(img.reshape(img.shape[:2]), cv2.COLOR_GRAY2BGR)
    h, w = img.shape[:2]
    if min(h, w) < MIN_SIZE:
        raise InputError(f"image too small to match: {w}x{h} px, need at least {MIN_SIZE} px on each side: {path}")
    if h * w > MAX_PIXELS:
        raise InputError(f"image too large: {w}x{h} px, at most {MAX_PIXELS // 1_000_000} megapixels: {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey of an RGB image."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def edge_share(image: np.ndarray, sigma: float = 0.7, level: float = EDGE_LEVEL) -> float:
    """Share of pixels whose intensity changes by more than ``level`` per pixel (x or y)."""
    g = to_gray(image).astype(np.float32)
    if sigma > 0:
        g = cv2.GaussianBlur(g, (0, 0), sigma)
    if min(g.shape) < 3:
        return 0.0
    dx = np.abs(g[1:-1, 2:] - g[1:-1, :-2])
    dy = np.abs(g[2:, 1:-1] - g[:-2, 1:-1])
    edge = np.maximum(dx, dy) > 2.0 * level
    return float(edge.mean())


def check_texture(image: np.ndarray, name: str, min_share: float = MIN_EDGE_SHARE) -> float:
    """Refuse a (nearly) textureless image with an :class:`InputError`; returns its edge share."""
    share = edge_share(image)
    if share < min_share:
        raise InputError(
            f"{name} is nearly textureless: {100 * share:.2f} % of its pixels lie on an intensity edge, "
            f"at least {100 * min_share:.1f} % are needed (a blank, flat or heavily blurred image cannot be matched)"
        )
    return share
