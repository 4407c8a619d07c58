"""Read the real stereo pairs with ground truth (``../shared/data/real_gt`` layout).

``middlebury2006/<scene>/``: ``view1.png``, ``view5.png``, ``disp1.png``, ``disp5.png``
(8-bit, disparity = value / 3, 0 = unknown); occlusion by the left-right check of
disp1 against disp5. ``middlebury2001/<scene>/``: ``imL.png``, ``imR.png``,
``groundtruth.png`` (disparity = value / scale, the scale on ``info.txt``'s first
line, 0 = unknown), ``nonocc.png`` (255: visible in both), ``all.png`` (255: valid).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..realgt import RealPair, lr_occlusion
from .images import read_image

logger = logging.getLogger(__name__)

__all__ = ["DEFAULT_REAL_GT", "MIDDLEBURY2006_SCALE", "list_pairs", "load_pair"]

#: Where the data lives beside a checkout of the project (never copied into it).
DEFAULT_REAL_GT = Path(__file__).resolve().parents[3] / "shared" / "data" / "real_gt"
#: Middlebury 2006 third-size disparity PNGs hold three times the disparity.
MIDDLEBURY2006_SCALE = 3.0


def _grey(path: Path) -> np.ndarray:
    data = np.fromfile(str(path), np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if img is None:
        raise InputError(f"cannot read the ground-truth image {path}")
    return img


def _disparity(path: Path, scale: float) -> np.ndarray:
    d = _grey(path).astype(np.float64) / scale
    d[d == 0] = np.nan
    return d


def list_pairs(root: str | os.PathLike) -> list[Path]:
    """The pair folders under ``root``, sorted by name (2006 first, then 2001)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"real ground-truth folder not found: {root}")
    out = sorted(p for p in (root / "middlebury2006").glob("*") if (p / "disp1.png").is_file())
    out += sorted(p for p in (root / "middlebury2001").glob("*") if (p / "groundtruth.png").is_file())
    if not out:
        raise InputError(f"no Middlebury pair in {root} (expected middlebury2006/*/disp1.png or "
                         f"middlebury2001/*/groundtruth.png)")
    return out


def load_pair(folder: str | os.PathLike) -> RealPair:
    """One published pair: images, disparity of image 1 (NaN = unknown) and its occlusions."""
    folder = Path(folder)
    if (folder / "disp1.png").is_file():
        disp = _disparity(folder / "disp1.png", MIDDLEBURY2006_SCALE)
        occluded = lr_occlusion(disp, _disparity(folder / "disp5.png", MIDDLEBURY2006_SCALE))
        img1, img2 = read_image(folder / "view1.png"), read_image(folder / "view5.png")
    else:
        scale = float((folder / "info.txt").read_text().split()[0])
        disp = _disparity(folder / "groundtruth.png", scale)
        disp[_grey(folder / "all.png") < 128] = np.nan
        occluded = np.isfinite(disp) & (_grey(folder / "nonocc.png") < 128)
        img1, img2 = read_image(folder / "imL.png"), read_image(folder / "imR.png")
    if img1.shape != img2.shape or img1.shape[:2] != disp.shape:
        raise InputError(f"{folder}: images and ground truth differ in size")
    return RealPair(folder.name, img1, img2, disp, occluded)
