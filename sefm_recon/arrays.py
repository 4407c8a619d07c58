"""Small array helpers shared by the stages."""

from __future__ import annotations

import numpy as np


def finite_rows(*arrays: np.ndarray) -> np.ndarray:
    """(N,) bool: rows that are finite in every one of the (N, k) float arrays.

    A row's sum is finite exactly when all its entries are; summing by a
    matrix-vector product is several times faster than ``isfinite().all(1)``
    on millions of short rows.
    """
    total = np.zeros(len(arrays[0]))
    for a in arrays:
        total += np.asarray(a, np.float64) @ np.ones(a.shape[1])
    return np.isfinite(total)
