"""What machine a measurement ran on: the CPU's model name, its cores and the date, for benchmark output files."""

from __future__ import annotations

import datetime
import os
from pathlib import Path


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``'s ``model name``), or ``unknown CPU`` where it is not given."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return "unknown CPU"
    return next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), "unknown CPU")


def machine_line() -> str:
    """Today's date, the CPU and its number of cores, as benchmark output files open: ``<YYYY-MM-DD>, <CPU>, <n> cores``."""
    return f"{datetime.date.today().isoformat()}, {cpu_name()}, {os.cpu_count()} cores"
