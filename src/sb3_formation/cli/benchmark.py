"""``sb3-formation benchmark``: targets on the thesis's stage 3 and every scene family, one table."""

from __future__ import annotations

import argparse
from pathlib import Path

from sb3_formation.cli.common import (
    add_disturbances_option,
    add_recipe_option,
    add_scene_sets_option,
    add_trust_pickle_option,
    agents_count,
    episodes_count,
    label_folders,
    model_trust,
    target_labels,
    teams_count,
)
from sb3_formation.env.scenes import BENCHMARK_SCENES
from sb3_formation.experiment.benchmark import BENCHMARK_EPISODES, BENCHMARK_SEED, TABLE_FILE, run_benchmark
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.arguments import output_path, seed_value
from sb3_formation.utils.files import folder_lock, holds_files


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``benchmark`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "benchmark",
        help="every target on every scene set of the benchmark: success (95%% CI), shape error, contacts, steps",
        description="Evaluate each target at stage 3 on the benchmark's scene sets "
        f"({', '.join(BENCHMARK_SCENES)}) with fixed seeds; print one table, write it with every evaluation and "
        "a trajectory figure per target and family into --out.",
    )
    parser.add_argument("targets", nargs="+", help="run folders, model .zip files or <kind>:<name> targets")
    parser.add_argument(
        "--episodes", type=episodes_count, default=BENCHMARK_EPISODES, help=f"per family (default {BENCHMARK_EPISODES})"
    )
    parser.add_argument(
        "--seed", type=seed_value, default=BENCHMARK_SEED, help=f"episode k plays seed + k (default {BENCHMARK_SEED})"
    )
    parser.add_argument("--agents", type=agents_count, help="team size (default: each target's own)")
    parser.add_argument("--n-envs", type=teams_count, default=16, help="teams played at once (default 16)")
    parser.add_argument("--workers", type=teams_count, default=2, help="processes stepping the teams (default 2)")
    parser.add_argument("--labels", help="comma-separated label per target (default: the targets)")
    parser.add_argument(
        "--out", type=output_path, default=output_path("benchmark"), help="a new or empty folder (default benchmark/)"
    )
    parser.add_argument("--device", default="auto", help="torch device (default auto)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_scene_sets_option(parser)
    add_disturbances_option(parser)
    add_recipe_option(parser, "recipe of controller: targets (default ch5-bearing)")
    add_trust_pickle_option(parser)
    parser.set_defaults(run=run)


def starting(args: argparse.Namespace) -> str:
    """The line ``benchmark`` starts with."""
    return f"benchmarking {', '.join(args.targets)} into {args.out} (Ctrl-C stops it)"


def run(args: argparse.Namespace) -> int:
    """``sb3-formation benchmark TARGET...``: the table, the evaluations and the figures, with ``--out`` locked from
    the check that it is new or empty to the last figure (a second benchmark into it is refused)."""
    targets = [Target.parse(target).with_recipe(args.recipe) for target in args.targets]
    labels = target_labels(args.labels, targets)
    folders = label_folders(labels)
    check_new_folder(args.out)
    with model_trust(args):
        for target in targets:  # every target loads before any is evaluated
            target.load(args.device)
        with folder_lock(args.out, "benchmark folder", remove=True):
            check_new_folder(args.out)  # again, now that no other benchmark can start writing here
            rows = run_benchmark(
                targets,
                folders,
                args.out,
                episodes=args.episodes,
                seed=args.seed,
                n_agents=args.agents,
                n_envs=args.n_envs,
                workers=args.workers,
                recipe=args.recipe,
                device=args.device,
                progress_bar=not args.no_progress,
                command=args.command_line,
                disturbances=args.disturbances or "ideal",
                scenes=args.scenes,
            )
            from sb3_formation.viz.plots import plot_trajectory, save_figures  # matplotlib: only where one is drawn

            figures = {
                args.out / "figures" / f"{row.label}_{row.scenes}.png": plot_trajectory(row.result.trajectories, 0)
                for row in rows
                if row.result.trajectories is not None
            }
            save_figures(figures)
    print((args.out / TABLE_FILE).read_text().rstrip())
    print(f"table written to {args.out / TABLE_FILE}, figures to {args.out / 'figures'}")
    return 0


def check_new_folder(out: Path) -> None:
    """Refuse an ``--out`` that holds files (:func:`~sb3_formation.utils.files.holds_files`).

    :raises ValueError: ``out`` is a file or holds files
    """
    if holds_files(out):
        raise ValueError(f"{out} already holds files: give a new or empty --out (nothing was written)")
