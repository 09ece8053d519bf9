"""``sb3-formation pretrained``: list the shipped policies, or export one."""

from __future__ import annotations

import argparse
from pathlib import Path

from sb3_formation.cli.common import print_summary
from sb3_formation.env.scenes import SCENES
from sb3_formation.experiment.export import export_pretrained
from sb3_formation.experiment.pretrained import pretrained_card, pretrained_names
from sb3_formation.utils.arguments import path_value


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``pretrained`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "pretrained",
        help="list the trained policies shipped with the package (pretrained:<name> targets), or export one",
        description="List the shipped policies with their stored evaluation (their recipe's protocol), or with --export "
        "make one of a finished run: its model without optimiser state, its ONNX export, its normaliser, settings, a "
        "fresh evaluation of that model file and a card recording the command, seed, wall time and versions.",
    )
    parser.add_argument("--export", type=Path, metavar="RUN_DIR", help="a finished run folder to ship")
    parser.add_argument("--name", help="name of the exported policy (pretrained:<name>)")
    parser.add_argument(
        "--into", type=path_value, help="folder of shipped policies to list or export into (default: the package's)"
    )
    parser.add_argument("--replace", action="store_true", help="with --export: replace a policy of that name")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``sb3-formation pretrained``: the shipped policies with their stored figures, or ``--export`` of a run."""
    options = {} if args.into is None else {"root": args.into}
    if args.export is not None or args.name is not None or args.replace:
        if args.export is None or args.name is None:
            raise ValueError("--export RUN_DIR and --name NAME go together")
        folder = export_pretrained(
            args.export, args.name, command=args.command_line, progress_bar=True, replace=args.replace, **options
        )
        print(f"pretrained:{args.name} written to {folder}")
        card = pretrained_card(args.name, folder.parent)
        print_summary(card["summary"])
        return 0
    columns = "target | recipe | n | episodes | success (95 % CI) | angle error (deg) | bearing error | agent contacts | steps"
    print(f"| {columns} | training |\n|---|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for name in pretrained_names(**options):
        card = pretrained_card(name, **options)
        summary = card["summary"]
        low, high = summary["success_rate_ci95"]
        means = {key: value["mean"] for key, value in summary["successful_episodes"].items()}  # None: no success
        contacts = summary["all_episodes"]["collisions_agent"]["mean"]
        sizes = card.get("team_sizes", [card["n_agents"]])
        n = f"{card['n_agents']} (trained on {', '.join(map(str, sizes))})" if len(sizes) > 1 else card["n_agents"]
        scenes = summary["scenes"]
        episodes = f"stage {summary['stage']}" if SCENES[scenes].staged else f"{scenes} scenes"
        print(
            f"| pretrained:{name} | {card['recipe']} | {n} | {episodes} | {summary['success_rate']:.1%} "
            f"({low:.1%}-{high:.1%}) | {figure(means['angle_error_deg'], '.2f')} | {figure(means['bearing_error'], '.4f')} | "
            f"{contacts:.3g} | {figure(means['length'], '.0f')} | {card['training_seconds'] / 60:.1f} min |"
        )
    return 0


def figure(value: float | None, spec: str) -> str:
    """``value`` formatted, or ``-`` where there is none (a mean over no successful episode)."""
    return "-" if value is None else format(value, spec)
