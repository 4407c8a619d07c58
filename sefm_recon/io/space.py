"""A full disk: free space checked before the results are written, and every writer's file after.

open3d and pycolmap report success on a file the disk had no room for (they
ignore the failed writes), and the C libraries print a line per failed write.
So the orchestration asks :func:`require_space` for an estimate of the bytes
it is about to write, each writer compares its file with the size it must have
(:func:`check_written`), and the staging folder turns a failure on a full disk
into one :class:`NoSpaceError` (exit code 2), with nothing written into OUT.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import shutil
import sys
import tempfile
import threading
from pathlib import Path
from typing import Iterator

from ..errors import InputError

#: errno values of a full disk or an exhausted quota.
NO_SPACE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
#: Slack on an estimate: file system blocks, headers, a PNG's size varying with the picture.
SLACK_FACTOR, SLACK_BYTES = 1.1, 1 << 20

_stderr_lock = threading.Lock()


class NoSpaceError(InputError):
    """Not enough free space for the results (one line, exit code 2)."""


def _mb(n: float) -> int:
    return max(1, math.ceil(n / (1 << 20)))


def free_bytes(folder: str | os.PathLike) -> int | None:
    """Free space for an unprivileged user on ``folder``'s file system; None when unknown."""
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def no_space_message(where, needed: int, free: int | None) -> str:
    """The one line; ``needed`` at most ``free`` (an estimate that proved too low) says "more than free"."""
    if free is None:
        return f"no space left on the device: {_mb(needed)} MB needed for the results in {where}"
    amount = f"{_mb(needed)} MB" if needed > free else f"more than {_mb(free)} MB"
    return f"no space left on the device: {amount} needed for the results in {where}, {_mb(free)} MB free"


def require_space(folder: str | os.PathLike, estimate: int, where=None) -> int:
    """Raise :class:`NoSpaceError` unless ``folder``'s file system has room for ``estimate`` bytes and slack.

    Returns the bytes asked for (the estimate with its slack).
    """
    needed = int(estimate * SLACK_FACTOR) + SLACK_BYTES
    free = free_bytes(folder)
    if free is not None and free < needed:
        raise NoSpaceError(no_space_message(where if where is not None else folder, needed, free))
    return needed


def check_written(path: str | os.PathLike, min_bytes: int) -> None:
    """Raise ``OSError`` when a writer that reported success left ``path`` shorter than ``min_bytes``.

    The errno is ENOSPC when the missing bytes would not fit on the device (a
    full disk, the usual cause), else EIO.
    """
    path = Path(path)
    size = path.stat().st_size if path.exists() else 0
    if size >= min_bytes:
        return
    free = free_bytes(path.parent)
    code = errno.ENOSPC if free is not None and free < min_bytes - size + SLACK_BYTES else errno.EIO
    raise OSError(code, f"{os.strerror(code)}: {path.name} has {size} of its {min_bytes} bytes")


def is_disk_full(err: BaseException | None) -> bool:
    """True when ``err`` or an exception it wraps is a full disk or an exhausted quota."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, OSError) and err.errno in NO_SPACE_ERRNOS:
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def tree_bytes(folder: str | os.PathLike) -> int:
    """Bytes of the files under ``folder`` (0 when it is gone)."""
    total = 0
    for root, _, files in os.walk(folder):
        for name in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, name)).st_size
    return total


@contextlib.contextmanager
def captured_stderr() -> Iterator[list[str]]:
    """Capture what C libraries print to file descriptor 2 (libjpeg's warnings, RPly's failed writes).

    On exit the yielded list holds the text, whitespace collapsed, as one
    string. When fd 2 cannot be redirected (or no temporary file can be made:
    a full disk), the text goes to ``/dev/null`` or where it went before.
    """
    captured: list[str] = []
    with _stderr_lock:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError):  # no usable fd 2
            yield captured
            return
        try:
            sink = tempfile.TemporaryFile()
        except OSError:
            sink = open(os.devnull, "w+b")
        with sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield captured
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                with contextlib.suppress(OSError, ValueError):
                    sink.seek(0)
                    captured.append(" ".join(sink.read().decode("utf-8", "replace").split()))
