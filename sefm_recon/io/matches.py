"""A pair's matches as ``matches.npz``: ``uv1``, ``uv2`` (N, 2) and ``score`` (N,), float32."""

from __future__ import annotations

import os
import zipfile

import numpy as np

__all__ = ["write_matches"]

#: Rows converted to float32 and written at a time: one buffer reused from block to block.
#: Converting the bench pair's 2.6 M matches whole took 0.33 s the first time in a process and
#: 0.13 s the second, most of it in the kernel filling the copies' 52 MB of new pages; block
#: by block, 0.03 s.
_WRITE_BLOCK = 1 << 18


def write_matches(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    """Write ``arrays`` (name -> array of any real dtype) into the uncompressed ``.npz`` file
    ``path`` as float32, the file :func:`numpy.savez` writes of their float32 copies
    (read with :func:`numpy.load`)."""
    f32 = np.dtype(np.float32)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, a in arrays.items():
            a = np.asarray(a)
            buf = np.empty((min(len(a), _WRITE_BLOCK), *a.shape[1:]), f32)
            with zf.open(name + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array_header_1_0(
                    f, {"descr": np.lib.format.dtype_to_descr(f32), "fortran_order": False, "shape": a.shape})
                for s in range(0, len(a), _WRITE_BLOCK):
                    block = buf[:min(_WRITE_BLOCK, len(a) - s)]
                    np.copyto(block, a[s:s + len(block)], casting="same_kind")
                    f.write(block.data)
