"""The ``sb3-formation`` command line: a thin layer over functions a notebook can call with the same names.

One module per subcommand, each with ``add_parser(commands)`` (its options, and ``run`` as the parser's default),
``run(args)`` (what it does) and, for the commands that work for a while, ``starting(args)`` (the first line they print:
what they are about to do); :mod:`~sb3_formation.cli.common` holds what several share.

Importing this module loads nothing heavy: :func:`main` takes Ctrl-C in hand first
(:func:`~sb3_formation.utils.interrupts.remember_ctrl_c`), then imports the subcommands (torch, Stable-Baselines3), so
that Ctrl-C at any moment of a command, its first seconds included, ends it with one line and exit code 130.
"""

from __future__ import annotations

import importlib
import os
import re
import shlex
import signal
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import TYPE_CHECKING

from sb3_formation.utils.interrupts import remember_ctrl_c

if TYPE_CHECKING:
    import argparse

#: The subcommands' modules (under ``sb3_formation.cli``), in the order ``--help`` lists them: each adds its parser,
#: which names its ``run``.
COMMANDS: tuple[str, ...] = ("train", "recipes", "pretrained", "evaluate", "plot", "render", "compare", "benchmark")
COMMANDS += ("robustness", "sweep", "rollout", "export", "ros")


def command_modules() -> list[ModuleType]:
    """The subcommands' modules, imported (this loads torch and Stable-Baselines3)."""
    return [importlib.import_module(f"sb3_formation.cli.{name}") for name in COMMANDS]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand (its errors are one line:
    :class:`~sb3_formation.utils.arguments.OneLineParser`)."""
    from sb3_formation.utils.arguments import OneLineParser

    parser = OneLineParser(
        prog="sb3-formation",
        description="Train, evaluate and look at shared-policy PPO formation control (one subcommand per task).",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    commands = parser.add_subparsers(dest="command", required=True)
    for command in command_modules():
        command.add_parser(commands)
    return parser


def _attach_negative_values(argv: list[str]) -> list[str]:
    """``--iterations -1,2,3`` as ``--iterations=-1,2,3``: argparse reads a value that starts with a dash and is not a
    plain negative number as an option (and says only "expected one argument"); attached, the option's own check
    names the problem."""
    joined: list[str] = []
    for token in argv:
        previous = joined[-1] if joined else ""
        if previous.startswith("--") and "=" not in previous and re.fullmatch(r"-[0-9.][^ ]*", token):
            joined[-1] = f"{previous}={token}"
        else:
            joined.append(token)
    return joined


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-formation`` console script.

    Ctrl-C is in hand before anything heavy is imported: at any moment it ends the command with one line,
    ``sb3-formation: <command> interrupted``, and exit code 130 (``--debug`` shows its traceback instead).
    """
    whole_process = argv is None  # the console script, not a caller in Python
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    with remember_ctrl_c():
        try:
            return _run(argv, debug)
        except KeyboardInterrupt:  # Ctrl-C outside training (which checkpoints first): stop with the shell's code
            if debug:
                raise
            print(f"sb3-formation: {_command_name(argv)} interrupted", file=sys.stderr)
    if whole_process:  # the command has unwound and said so: end the process with the shell's code at once, so that
        sys.stdout.flush()  # nothing in Python's shutdown (which gives SIGINT back its default action) can turn it
        sys.stderr.flush()  # into a death by signal
        os._exit(128 + signal.SIGINT)
    return 128 + signal.SIGINT


def _command_name(argv: list[str]) -> str:
    """The subcommand named in ``argv`` (what a Ctrl-C interrupted, maybe before the arguments were read)."""
    return next((token for token in argv if token in COMMANDS), "command")


def _run(argv: list[str], debug: bool) -> int:
    """Import the subcommands, read the arguments, say what the command is about to do, and run it."""
    from sb3_formation.experiment.training import TrainingStopped

    modules = dict(zip(COMMANDS, command_modules()))
    args = build_parser().parse_args(_attach_negative_values(argv))
    args.command_line = shlex.join(["sb3-formation", *argv])
    try:
        starting = getattr(modules[args.command], "starting", None)
        if starting is not None:
            print(starting(args), flush=True)
        return int(args.run(args))
    except TrainingStopped as stop:
        print(f"sb3-formation: {stop}", file=sys.stderr)
        return 128 + stop.signal_number
    except BrokenPipeError:  # the reader of the output left (``| head``): stop without a word, as a Unix tool does
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing left to flush at exit
        return 128 + signal.SIGPIPE
    # bad input, files, a failed worker, a missing optional package: one line
    except (ValueError, TypeError, OSError, RuntimeError, ImportError) as error:
        if debug:
            raise
        print(f"sb3-formation: error: {error}", file=sys.stderr)
        return 2
