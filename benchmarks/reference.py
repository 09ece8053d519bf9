"""A reference commit of this repository beside this checkout, so that a benchmark measures both in one run.

``reference_source(rev)`` checks the commit out into a temporary git worktree and yields its ``src/`` folder: put it
first on ``PYTHONPATH`` in a subprocess to run the reference's code with this virtual environment.
"""

from __future__ import annotations

import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@contextmanager
def reference_checkout(rev: str) -> Iterator[Path]:
    """The commit ``rev`` checked out into a temporary worktree (removed afterwards); yields its folder."""
    with tempfile.TemporaryDirectory() as folder:
        worktree = Path(folder) / "reference"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(worktree), rev], check=True, capture_output=True
        )
        try:
            yield worktree
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(worktree)], check=False)
