"""The predicates every validation uses: what counts as an integer or a real number in a config, a recipe or a flag.

A bool is never a number here: YAML's ``true`` must not become 1 m/s. Numpy scalars count as numbers.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np


def is_integer(value: Any) -> bool:
    """An integer (Python's or numpy's), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def is_count(value: Any) -> bool:
    """An integer >= 0, not a bool."""
    return is_integer(value) and value >= 0


def is_real(value: Any) -> bool:
    """A real number (integers included, infinities and NaN too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def is_number(value: Any) -> bool:
    """A finite real number, not a bool."""
    return is_real(value) and math.isfinite(value)
