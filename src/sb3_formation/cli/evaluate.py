"""``sb3-formation evaluate``: evaluate a policy on fixed-seed episodes."""

from __future__ import annotations

import argparse

from sb3_formation.cli.common import (
    TARGET_HELP,
    add_protocol_arguments,
    agents_count,
    evaluate_with_protocol,
    model_trust,
    print_summary,
)
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.arguments import output_path


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``evaluate`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "evaluate",
        help="evaluate a trained policy: success rate with a 95%% interval, errors, episodes.csv, trajectories",
        description="Play fixed-seed episodes (episode k from seed + k) with a trained policy and write "
        "summary.json (success rate with a 95%% Wilson interval; mean and std of errors, steps and collisions), "
        "episodes.csv (one row per episode) and trajectories.npz (every step of the first episodes).",
    )
    parser.add_argument("target", help=TARGET_HELP)
    add_protocol_arguments(parser)
    parser.add_argument(
        "--agents", type=agents_count, help="team size (default: the model's; another only for one trained on several)"
    )
    parser.add_argument(
        "--trajectories",
        type=int,  # the protocol refuses more than 100, saying why (memory)
        default=5,
        metavar="K",
        help="record every step of the first K episodes (default 5)",
    )
    parser.add_argument("--out", type=output_path, help="folder for the files (default: <run>/eval)")
    parser.set_defaults(run=run)


def starting(args: argparse.Namespace) -> str:
    """The line ``evaluate`` starts with."""
    return f"evaluating {args.target} (Ctrl-C stops it)"


def run(args: argparse.Namespace) -> int:
    """``sb3-formation evaluate``: success rate with a Wilson interval, errors, episode table and trajectories."""
    with model_trust(args):
        print_summary(evaluate_with_protocol(args, Target.parse(args.target, args.recipe), out=args.out))
    return 0
