"""The predicates every validation uses: what counts as an integer or a real number in a config, a recipe or a flag.

A bool is never a number here: YAML's ``true`` must not become 1 m/s. Numpy scalars count as numbers.
"""

from __future__ import annotations

import math
import numbers
import os
from pathlib import Path
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


#: The longest file or folder name (bytes) the usual file systems take (ext4, XFS, APFS, NTFS in UTF-16 units).
MAX_NAME_BYTES = 255


def check_path(path: str | os.PathLike[str], what: str) -> None:
    """Refuse a path the package could not write its records under: an empty one (it would stand for the working
    folder), a name that is not valid UTF-8 (from bytes the shell passed through), or a part longer than
    :data:`MAX_NAME_BYTES`. The one check of every path a command writes to (the command line's
    :func:`~sb3_formation.utils.arguments.output_path` and the settings' folders).

    :param path: the path
    :param what: what it is (an option, a setting), for the message
    :raises ValueError: naming the problem
    """
    text = os.fspath(path)
    if not text.strip():
        raise ValueError(f"{what} is empty: name a file or folder (. for the working folder)")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"{what} {text!r} is not valid UTF-8: give a name of UTF-8 characters") from None
    for part in Path(text).parts:
        if len(part.encode("utf-8")) > MAX_NAME_BYTES:
            raise ValueError(f"{what}: the name {part[:40]!r}... is longer than {MAX_NAME_BYTES} bytes")


def check_name(name: str, what: str) -> None:
    """Refuse a name that is not one file or folder name inside its parent: empty, ``.``, ``..``, or holding a path
    separator or a NUL (a label that becomes a folder under ``--out`` must stay under it).

    :param name: the name
    :param what: what it is (an option, a setting), for the message
    :raises ValueError: naming the problem
    """
    if name in ("", ".", "..") or any(character in name for character in ("/", "\\", "\0")):
        raise ValueError(f"{what} {name!r} is not a single file name: give letters, digits, '.', '-' or '_'")
    check_path(name, what)
