"""A Ctrl-C that lands in a finaliser is dropped by Python; :mod:`sb3_formation.utils.interrupts` raises it again."""

from __future__ import annotations

import gc
import os
import signal
from collections.abc import Iterator

import pytest

from sb3_formation.utils.interrupts import raise_if_interrupted, remember_ctrl_c


class InterruptedWhileFreed:
    """Gets SIGINT while it is freed, as a Pymunk body freed from a cffi callback when an episode's world is collected."""

    def __del__(self) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        sum(range(10_000))  # Python runs the handler here, inside the finaliser, which drops its KeyboardInterrupt


@pytest.fixture
def ctrl_c_handled() -> Iterator[None]:
    """SIGINT handled as in a terminal (Python's default handler), also where the test runner was started in the
    background, which leaves SIGINT ignored (and ``remember_ctrl_c`` then, rightly, changes nothing)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.usefixtures("ctrl_c_handled")
def test_a_ctrl_c_dropped_in_a_finaliser_is_raised_at_the_next_check(capsys: pytest.CaptureFixture[str]) -> None:
    with remember_ctrl_c():
        InterruptedWhileFreed()
        gc.collect()
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted()
    raise_if_interrupted()  # the flag ends with the block
    assert "Exception ignored" not in capsys.readouterr().err  # no traceback for the dropped one
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
