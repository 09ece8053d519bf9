"""The ``sb3-formation`` command line: a thin layer over functions a notebook can call with the same names.

One module per subcommand, each with ``add_parser(commands)`` (its options, and ``run`` as the parser's default) and
``run(args)`` (what it does);
:mod:`~sb3_formation.cli.common` holds what several share.
"""

from __future__ import annotations

import argparse
import re
import shlex
import signal
import sys
from collections.abc import Sequence

from sb3_formation.cli import (
    benchmark,
    compare,
    evaluate,
    export,
    plot,
    pretrained,
    recipes,
    render,
    rollout,
    ros,
    sweep,
    train,
)
from sb3_formation.experiment.training import TrainingStopped
from sb3_formation.utils.interrupts import remember_ctrl_c

#: The subcommands' modules, in the order ``--help`` lists them: each adds its parser, which names its ``run``.
COMMANDS = (train, recipes, pretrained, evaluate, plot, render, compare, benchmark, sweep, rollout, export, ros)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="sb3-formation",
        description="Train, evaluate and look at shared-policy PPO formation control (one subcommand per task).",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    commands = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
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
    """Entry point of the ``sb3-formation`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(_attach_negative_values(argv))
    args.command_line = shlex.join(["sb3-formation", *argv])
    try:
        with remember_ctrl_c():
            return args.run(args)
    except TrainingStopped as stop:
        print(f"sb3-formation: {stop}", file=sys.stderr)
        return 128 + stop.signal_number
    except KeyboardInterrupt:  # Ctrl-C outside training (which checkpoints first): stop with the shell's code
        if args.debug:
            raise
        print(f"sb3-formation: {args.command} interrupted", file=sys.stderr)
        return 128 + signal.SIGINT
    # bad input, files, a failed worker, a missing optional package: one line
    except (ValueError, TypeError, OSError, RuntimeError, ImportError) as error:
        if args.debug:
            raise
        print(f"sb3-formation: error: {error}", file=sys.stderr)
        return 2
