"""Whether numba's on-disk cache holds the package's compiled kernels.

The numba kernels (``@njit(cache=True)``) are compiled on their first call and the
machine code is cached beside the source; a fresh install compiles them once, in
silence. The command line looks here first so that it can say so before it starts.
The test is cheap and does not import numba: a module's kernels count as cached when
numba has an index file (``<module>.<function>-<line>.py<version>.nbi``) for it that
is at least as new as the source, in the folder numba itself would use.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Iterable
from pathlib import Path

#: The package's folder, as ``__file__`` names it (numba hashes that path, unresolved).
PACKAGE = Path(os.path.abspath(__file__)).parents[1]
#: A decorator line of a cached kernel: ``@njit(cache=True)``, ``@numba.njit(parallel=True, cache=True)``.
_KERNEL = re.compile(r"^\s*@(?:numba\.)?n?jit\(.*\bcache=True", re.MULTILINE)


def kernel_sources(root: Path = PACKAGE) -> list[Path]:
    """The modules below ``root`` that hold cached numba kernels."""
    return sorted(p for p in root.rglob("*.py") if _KERNEL.search(p.read_text(encoding="utf-8", errors="ignore")))


def cache_dirs(source: Path) -> list[Path]:
    """Where numba keeps the cache of ``source``'s kernels, in the order its locators try them:
    ``$NUMBA_CACHE_DIR/<folder>_<sha1 of the folder's path>`` when that is set; else the
    ``__pycache__`` beside the source, or the same sub-folder of the user's cache folder when
    ``__pycache__`` is not writable."""
    folder = Path(os.path.abspath(source)).parent
    sub = f"{folder.name}_{hashlib.sha1(str(folder).encode()).hexdigest()}"
    if os.environ.get("NUMBA_CACHE_DIR"):
        return [Path(os.path.abspath(os.environ["NUMBA_CACHE_DIR"])) / sub]
    user = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "numba" / sub
    return [folder / "__pycache__", user]


def is_cached(source: Path) -> bool:
    """numba holds an index of ``source``'s kernels written after the source's last change."""
    changed = source.stat().st_mtime
    for folder in cache_dirs(source):
        try:
            if any(index.stat().st_mtime >= changed for index in folder.glob(f"{source.stem}.*.nbi")):
                return True
        except OSError:  # an unreadable cache folder is a cold one
            continue
    return False


def cold_kernels(sources: Iterable[Path]) -> list[Path]:
    """The modules among ``sources`` whose kernels the next call will compile."""
    return [s for s in sources if not is_cached(s)]
