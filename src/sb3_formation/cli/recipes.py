"""``sb3-formation recipes``: list the shipped recipes."""

from __future__ import annotations

import argparse

from sb3_formation.experiment.recipes import load_recipe, recipe_names


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``recipes`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "recipes",
        help="list the recipes --recipe can name",
        description="List the recipes shipped with the package (a recipe YAML file's path works as --recipe too).",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``sb3-formation recipes``: the shipped recipes, one line each."""
    names = recipe_names()
    width = max(len(name) for name in names)
    for name in names:
        print(f"{name:<{width}}  {load_recipe(name).description}")
    return 0
