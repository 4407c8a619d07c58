"""Small array helpers shared by the stages."""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit


def finite_rows(*arrays: np.ndarray) -> np.ndarray:
    """(N,) bool: rows that are finite in every one of the (N, k) float arrays.

    A row's sum is finite exactly when all its entries are; summing by a
    matrix-vector product is several times faster than ``isfinite().all(1)``
    on millions of short rows. Where each array's sum is finite, so is every
    entry, and the rows are not summed (a sixth of the time on the bench
    pair's 2.6 million matches).
    """
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf and overflow: non-finite, as meant
        if all(np.isfinite(np.sum(a)) for a in arrays):
            return np.ones(len(arrays[0]), bool)
        total = np.zeros(len(arrays[0]))
        for a in arrays:
            total += np.asarray(a, np.float64) @ np.ones(a.shape[1])
    return np.isfinite(total)


def append_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` followed by the rows of ``b``, without copying ``a`` where it can be.

    Where ``a`` is a leading slice of a C-contiguous array with room for ``b`` after it
    (as :func:`sefm_recon.matching.readback.pixel_matches` returns its arrays), ``b`` is written
    into that room and the longer slice returned; the caller owns the room. Otherwise a
    concatenation. Appending a few thousand rows to millions copies only those.
    """
    base = a.base
    n = len(a) + len(b)
    if (isinstance(base, np.ndarray) and base.dtype == a.dtype and base.shape[1:] == a.shape[1:]
            and base.flags.c_contiguous and a.flags.c_contiguous and len(base) >= n
            and a.ctypes.data == base.ctypes.data):
        out = base[:n]
        out[len(a):] = b
        return out
    return np.concatenate([a, b])


@njit(cache=True)
def _to_front(a, idx):
    for j in range(len(idx)):  # (idx rises: a row moves forward only, over rows already moved)
        a[j] = a[idx[j]]


def keep_rows(keep: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The rows of each array (N, ...) where ``keep`` (N,) bool holds, moved to its front in
    place, in order: leading slices of the arrays, so that :func:`append_rows` still writes
    into the room after them, and no copy of millions of rows in fresh pages."""
    idx = np.flatnonzero(keep)
    for a in arrays:
        _to_front(a, idx)
    return tuple(a[:len(idx)] for a in arrays)


def quiet_windows(gray: np.ndarray, size: int, levels: float) -> np.ndarray:
    """(H, W) bool: pixels of ``gray`` (H, W) whose ``size`` square window has a grey-value
    standard deviation below ``levels`` (its borders reflected, as OpenCV's box filter does)."""
    g = gray.astype(np.float32)
    win = (size, size)
    mean = cv2.blur(g, win)
    var = cv2.blur(cv2.multiply(g, g), win)  # (OpenCV's sqrBoxFilter took twice as long)
    var -= cv2.multiply(mean, mean)
    return var < levels**2
