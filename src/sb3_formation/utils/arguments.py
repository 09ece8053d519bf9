"""Command-line values every command reads alike: counts bounded by a documented maximum, seeds, output paths, and a
parser whose errors are one line (no torch: ``python -m sb3_formation.ros`` uses it too).

A count option takes an integer in ``[1, maximum]``: a larger one would overflow a C integer or allocate without bound
(``--episodes 10**30``). An output path must be a name the package can write its records under: not empty (``--out ""``
would be the working folder), valid UTF-8, no part longer than 255 bytes
(:func:`~sb3_formation.utils.checks.check_path`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from sb3_formation.utils.checks import check_path
from sb3_formation.utils.files import check_writable

#: The largest seed: numpy's and Gymnasium's seeds are unsigned 32-bit integers.
MAX_SEED = 2**32 - 1
#: The most episodes one command plays (an evaluation, a benchmark's scene set, a video, a ROS simulation): 200 times
#: the thesis's 500; each episode's row is held until its evaluation is written.
MAX_EPISODES = 100_000


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line on stderr, ``<program>: error: <what> (<prog> --help ...)``,
    exit code 2 (argparse's own prints its usage first); subcommands' parsers are of the same class."""

    def error(self, message: str) -> NoReturn:
        words = self.prog.split()
        program = words[2] if words[:2] == ["python", "-m"] else words[0]  # python -m sb3_formation.ros: the module
        self.exit(2, f"{program}: error: {message} (`{self.prog} --help` lists the options)\n")


def count(maximum: int, minimum: int = 1) -> Callable[[str], int]:
    """The type of an option that counts something: an integer in ``[minimum, maximum]``.

    :param maximum: the largest value (a documented constant, e.g. :data:`MAX_EPISODES`)
    :param minimum: the smallest value
    """

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not minimum <= value <= maximum:
            shown = str(value) if len(str(value)) <= 20 else f"{str(value)[:8]}... ({len(str(value))} digits)"
            raise argparse.ArgumentTypeError(f"must be an integer in [{minimum:,}, {maximum:,}], got {shown}")
        return value

    parse.__name__ = "count"
    return parse


#: A seed: an integer in [0, :data:`MAX_SEED`].
seed_value = count(MAX_SEED, minimum=0)


def bounded_float(low: float, high: float) -> Callable[[str], float]:
    """The type of a real option in ``[low, high]`` (NaN and infinities refused)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not low <= value <= high:  # NaN fails both
            raise argparse.ArgumentTypeError(f"must be a number in [{low:g}, {high:g}], got {text}")
        return value

    parse.__name__ = "number"
    return parse


def path_value(text: str) -> Path:
    """The type of an option naming a file or folder the command reads or writes
    (:func:`~sb3_formation.utils.checks.check_path`), checked as it is read."""
    try:
        check_path(text, "the path")
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return Path(text)


path_value.__name__ = "path"


def output_path(text: str) -> Path:
    """The type of an option naming a file or folder to write: :func:`path_value`, and not inside the installed package
    (:func:`~sb3_formation.utils.files.check_writable`), checked as it is read, before any work."""
    path = path_value(text)
    try:
        check_writable(path)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return path


output_path.__name__ = "path"
