"""One call in a child process forked beside this one, for library work that holds Python's lock.

COLMAP's CPU SIFT holds the interpreter lock, so a thread cannot run it beside other
work; a child forked from this process can, on a second core, with its own copy of
memory. Both processes then pay a page copy for every page either writes while the
child runs: the COLMAP model built in a child beside the other output files of the bench
pair took the write stage from 0.51 to 0.66 s while those files were packed into fresh
arrays the size of the matches (freed memory reused, so pages shared with the child),
and from 0.54 to 0.38 s once they were written through small buffers. The child runs
one function and sends its result back through a pipe (pickled); it dies with a Ctrl-C
or with this process. Where no child can run (not Linux, one core, no process to be
had) or the child gives nothing back (its call raised, its result does not pickle, it
was killed), the call runs in this process, which then raises what the call raises.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import sys
import warnings
from typing import Any, Callable

logger = logging.getLogger(__name__)


def can_fork() -> bool:
    """A child process can run beside this one: Linux (fork is safe for what the child does) and two or more cores."""
    return sys.platform.startswith("linux") and hasattr(os, "fork") and len(os.sched_getaffinity(0)) > 1


def _die_with_parent() -> None:
    """Linux: this (child) process gets SIGKILL when its parent ends (prctl PR_SET_PDEATHSIG)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


class Forked:
    """``with Forked(fn, *args) as job: ...; value = job.result()``: ``fn(*args)`` in a child
    process started here, its value returned by :meth:`result` (or the call made there,
    in this process, where the child could not run or gave nothing). Leaving the block
    without :meth:`result` (an exception, a Ctrl-C) kills the child."""

    def __init__(self, fn: Callable[..., Any], *args: Any):
        self.fn, self.args = fn, args
        self.pid: int | None = None
        self.reader = None
        if not can_fork():
            return
        r, w = os.pipe()
        for stream in (sys.stdout, sys.stderr):  # a child must not write the parent's buffered text again
            if stream is not None:
                stream.flush()
        with warnings.catch_warnings():  # Python >= 3.12 warns of fork in a threaded process (the child
            warnings.simplefilter("ignore", DeprecationWarning)  # runs one library call and a pipe only)
            try:
                pid = os.fork()
            except OSError:  # no process to be had (a limit, memory): the call runs here
                os.close(r)
                os.close(w)
                return
        if pid == 0:  # the child
            try:
                os.close(r)
                for sig in (signal.SIGINT, signal.SIGTERM):
                    signal.signal(sig, signal.SIG_DFL)
                _die_with_parent()
                with os.fdopen(w, "wb") as out:
                    pickle.dump(fn(*args), out, protocol=5)
            finally:
                os._exit(0)
        os.close(w)
        self.pid = pid
        self.reader = os.fdopen(r, "rb")

    def result(self) -> Any:
        """The call's value: the child's, or the call made here."""
        if self.pid is None:
            return self.fn(*self.args)
        value, got = None, False
        with self.reader as inp:
            try:
                value, got = pickle.load(inp), True
            except (EOFError, pickle.UnpicklingError):
                logger.debug("child process of %s gave no result: called in this process",
                             getattr(self.fn, "__name__", self.fn))
        os.waitpid(self.pid, 0)
        self.pid = None
        return value if got else self.fn(*self.args)

    def __enter__(self) -> Forked:
        return self

    def __exit__(self, *exc) -> bool:
        if self.pid is not None:  # left early: the child goes too
            os.kill(self.pid, signal.SIGKILL)
            os.waitpid(self.pid, 0)
            self.reader.close()
            self.pid = None
        return False
