"""Test-session recipe: one torch thread per pytest-xdist worker.

With ``pytest -n 2`` on 2 cores, two workers that each run torch's default of one thread per core oversubscribe the
machine, and torch's spinning threads then slow training down many times over (measured: the stage-1 learning test
took 86 s alone, 71-77 s as two copies with one thread each, and over 12 minutes as two copies with two threads each).
The variable also reaches the training and sweep processes the tests start.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = "1"

import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """Run the test on one torch thread (then restore the count): recorded parameters and measured learning results
    depend on it, since torch's sums round differently on one thread and on two."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
