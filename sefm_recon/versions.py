"""The versions of Python and of the libraries whose code computes the results.

The matcher's figures depend on them, not only on sefm-recon's own code: OpenCV's SGM,
warps and filters decide where the plain regions' planes align (docs/results.md, "Library
versions"). Reports and evaluation tables carry them, so that a figure can be reproduced.
"""

from __future__ import annotations

import platform
from importlib import metadata

from . import __version__

#: Library name -> the distributions that install it, in the order looked for (the first
#: installed one counts): OpenCV ships as several wheels of one module, open3d as two.
DISTRIBUTIONS = {
    "numpy": ("numpy",),
    "opencv": ("opencv-contrib-python-headless", "opencv-contrib-python", "opencv-python-headless",
               "opencv-python"),
    "numba": ("numba",),
    "pycolmap": ("pycolmap",),
    "open3d": ("open3d-cpu", "open3d"),
}


def library_versions() -> dict[str, str | None]:
    """``{"sefm-recon", "python", "numpy", "opencv", "numba", "pycolmap", "open3d"}`` -> version
    (None where not installed), read from the installed distributions' metadata without
    importing them."""
    out: dict[str, str | None] = {"sefm-recon": __version__, "python": platform.python_version()}
    for name, dists in DISTRIBUTIONS.items():
        out[name] = None
        for dist in dists:
            try:
                out[name] = metadata.version(dist)
                break
            except metadata.PackageNotFoundError:
                continue
    return out


def format_versions(versions: dict[str, str | None] | None = None) -> str:
    """One line for a report or table: ``"sefm-recon 0.1.0, python 3.11.7, numpy 2.4.6, ..."``."""
    versions = library_versions() if versions is None else versions
    return ", ".join(f"{k} {v or 'missing'}" for k, v in versions.items())
