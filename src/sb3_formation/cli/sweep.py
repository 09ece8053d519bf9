"""``sb3-formation sweep``: the seeds of a recipe on Ray."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sb3_formation.cli.common import indices, teams_count
from sb3_formation.utils.arguments import output_path


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``sweep`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "sweep",
        help="train and evaluate every seed of a recipe on Ray, then aggregate over the seeds",
        description="Run every seed of a recipe file (its run: seeds) as a Ray task (this machine, or a cluster with "
        "--address); each writes <logdir>/<file>/seed_<s>/, a normal run folder. Finished trials are skipped and "
        "interrupted ones resumed when the sweep is started again. Needs pip install 'sb3-formation[ray]'.",
    )
    parser.add_argument("recipe", type=Path, help="recipe YAML with a run: section, e.g. recipes/quick-ch5-bearing.yaml")
    parser.add_argument("--seeds", type=indices, help="comma-separated seeds (default: the recipe file's)")
    parser.add_argument("--address", help="address of a running Ray cluster (default: start Ray on this machine)")
    parser.add_argument("--max-concurrent", type=teams_count, help="trials at once (default: one per CPU)")
    parser.add_argument("--logdir", type=output_path, help="folder for the sweep's folder (default: the recipe file's logdir)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``sb3-formation sweep``: every (configuration x seed) trial on Ray; exit code 1 if a trial failed."""
    from sb3_formation.viz.plots import save_sweep_curves  # imported only by the command that uses it

    try:
        from sb3_formation.experiment.sweep import sweep
    except ImportError as error:  # pragma: no cover - without the extra
        raise ValueError(f"sweep needs Ray: pip install 'sb3-formation[ray]' ({error})") from error
    options = {"seeds": args.seeds, "address": args.address, "max_concurrent": args.max_concurrent, "logdir": args.logdir}
    try:
        result = sweep(args.recipe, **options)
    except KeyboardInterrupt:
        print("sb3-formation: sweep interrupted; run the same command again to finish it", file=sys.stderr)
        return 130
    for seed, failure in result.failed.items():
        print(f"sb3-formation: trial seed {seed} failed: {failure}", file=sys.stderr)
    curves = save_sweep_curves(result)
    if curves is not None:
        print(f"training curves: {curves}")
    print(f"sweep folder: {result.folder}")
    return 1 if result.failed else 0
