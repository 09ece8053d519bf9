"""``sb3-formation presets``: list the shipped set-ups."""

from __future__ import annotations

import argparse

from sb3_formation.experiment.setups import load_setup, setup_names


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``presets`` subcommand to ``commands``."""
    commands.add_parser(
        "presets",
        help="list the set-ups --preset can name",
        description="List the set-ups shipped with the package (a set-up YAML file's path works as --preset too).",
    )


def run(args: argparse.Namespace) -> int:
    """``sb3-formation presets``: the shipped set-ups, one line each."""
    names = setup_names()
    width = max(len(name) for name in names)
    for name in names:
        print(f"{name:<{width}}  {load_setup(name).description}")
    return 0
