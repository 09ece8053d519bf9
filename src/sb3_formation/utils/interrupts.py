"""Ctrl-C that is never lost.

Python raises ``KeyboardInterrupt`` wherever the main thread is when SIGINT arrives. Inside a finaliser (Pymunk frees
its bodies from a cffi callback when an episode's world is collected) the exception is printed and dropped, and the
command would play on. While :func:`remember_ctrl_c` is active, SIGINT also sets a flag that the episode loop checks
at every step (:func:`raise_if_interrupted`), so a dropped interrupt is raised again there (and its "exception
ignored" traceback is not printed).
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

_interrupted = threading.Event()


@contextlib.contextmanager
def remember_ctrl_c() -> Iterator[None]:
    """While the block runs, SIGINT raises ``KeyboardInterrupt`` and is remembered for :func:`raise_if_interrupted`;
    from then until the block ends, SIGINT is ignored (the block is being left: a second Ctrl-C would break the clean-up).

    Nothing changes where SIGINT is ignored (a background job) or outside the main thread.
    """
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the block is stopping: Ctrl-C again must not break its unwinding
        _interrupted.set()
        raise KeyboardInterrupt

    def quiet_about_interrupts(unraisable: Any) -> None:  # the dropped interrupt is raised again: no traceback
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            hook(unraisable)

    previous, hook = signal.signal(signal.SIGINT, interrupt), sys.unraisablehook
    sys.unraisablehook = quiet_about_interrupts
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = hook
        _interrupted.clear()


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` if SIGINT arrived inside :func:`remember_ctrl_c` (even where it was dropped)."""
    if _interrupted.is_set():
        raise KeyboardInterrupt
