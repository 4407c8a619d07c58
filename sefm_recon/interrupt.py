"""Ctrl-C and SIGTERM: recorded when they arrive, raised as :class:`KeyboardInterrupt`.

Python runs a signal handler at its next bytecode. A numba kernel does not
look at signals, so the handler runs when the kernel returns, and when that is
while numba boxes the kernel's result (a tuple of arrays calls back into
Python), the ``KeyboardInterrupt`` comes out wrapped in ``SystemError:
CPUDispatcher(...) returned a result with an exception set``. Other libraries
may wrap or swallow it too. So the handler also records the signal: the command
line treats any failure after a recorded signal as the interrupt it is
(:func:`caused_by_interrupt`), and :func:`check` raises it again at the points
where nothing may go on after an interrupt (before the results are committed).
"""

from __future__ import annotations

import contextlib
import signal
import threading

_received: list[int] = []


_holding = [0]  # blocks of :func:`held` running


def _handler(signum, frame):
    _received.append(signum)
    if not _holding[0]:
        raise KeyboardInterrupt


def install() -> None:
    """Handle SIGINT and SIGTERM in this (main) thread; elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:  # e.g. nohup, or a background job of a shell
            signal.signal(sig, _handler)


def received() -> int | None:
    """The first signal recorded by the handler, else None."""
    return _received[0] if _received else None


def caused_by_interrupt(err: BaseException) -> bool:
    """True when ``err`` is, wraps or follows a Ctrl-C / SIGTERM."""
    if received() is not None:
        return True
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def check() -> None:
    """Raise :class:`KeyboardInterrupt` if a signal was recorded (a library may have swallowed the first one)."""
    if received() is not None:
        raise KeyboardInterrupt


@contextlib.contextmanager
def held():
    """Hold Ctrl-C and SIGTERM back while the block runs: the handler records them, and the
    interrupt is raised as the block ends. For a step that must not be cut in two, such as
    starting jobs whose futures must all be known to be waited for."""
    before = len(_received)
    _holding[0] += 1
    try:
        yield
    finally:
        _holding[0] -= 1
    if not _holding[0] and len(_received) > before:
        raise KeyboardInterrupt
