"""The command line's memory allocator settings (glibc)."""

from __future__ import annotations

import ctypes
import logging
import os
import sys

logger = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1  # mallopt parameters, from glibc's malloc.h
_M_MMAP_MAX = -4


def keep_freed_memory() -> bool:
    """Have glibc serve large arrays from its heap and keep freed memory for reuse.

    By default glibc maps every allocation above its mmap threshold (at most
    32 MB) afresh and unmaps it when freed, so each large temporary array
    (millions of matches) pays a page fault per 4 KiB page on first touch.
    The matcher makes dozens of them per pair, and on large pairs those page
    faults are a sizeable share of the matching time.
    With mmap off and no trimming, freed memory stays in the process and is
    reused; the resident size stays at its peak until the process exits,
    which suits a command that runs one job and ends.

    Does nothing off Linux/glibc, or when the user set the allocator through
    ``MALLOC_*`` environment variables or ``GLIBC_TUNABLES``. Returns True
    when the settings were applied.
    """
    if not sys.platform.startswith("linux"):
        return False
    if "GLIBC_TUNABLES" in os.environ or any(k.startswith("MALLOC_") for k in os.environ):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_MAX, 0) == 1 and mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1
    logger.debug("glibc malloc: keep freed memory %s", "on" if ok else "failed")
    return ok


def release_freed_memory() -> None:
    """Give the memory that :func:`keep_freed_memory` keeps back to the system (glibc ``malloc_trim``).

    For measuring one job's peak memory after another in the same process.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
