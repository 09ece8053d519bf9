"""Starting a command as a terminal would, for the tests that press Ctrl-C on it."""

from __future__ import annotations

import signal


def default_ctrl_c() -> None:
    """``preexec_fn`` of ``subprocess.Popen``: the command starts with Ctrl-C's default action, as under a terminal.

    A background job of a non-interactive shell (``make test &``, a CI runner's job) starts with SIGINT ignored, and
    every process it starts inherits the ignore; Python then installs no ``KeyboardInterrupt`` handler, and a test
    that sends SIGINT would wait for a command that never hears it.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)
