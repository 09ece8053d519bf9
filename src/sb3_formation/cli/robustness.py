"""``sb3-formation robustness``: targets under a disturbance profile scaled level by level, curves and one table."""

from __future__ import annotations

import argparse

from sb3_formation.cli.benchmark import check_new_folder
from sb3_formation.cli.common import (
    add_recipe_option,
    add_scene_sets_option,
    add_trust_pickle_option,
    disturbances_source,
    episodes_count,
    label_folders,
    model_trust,
    target_labels,
    teams_count,
)
from sb3_formation.env.disturbances import PARTS
from sb3_formation.env.scenes import BENCHMARK_SCENES
from sb3_formation.experiment.benchmark import BENCHMARK_EPISODES, BENCHMARK_SEED
from sb3_formation.experiment.robustness import (
    FIGURES_FOLDER,
    MAX_LEVEL,
    RESULTS_FILE,
    ROBUSTNESS_LEVELS,
    TABLE_FILE,
    check_levels,
    check_robustness_inputs,
    level_name,
    run_robustness,
)
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.arguments import output_path, seed_value
from sb3_formation.utils.files import folder_lock

#: ``--levels``' default, as it is written.
DEFAULT_LEVELS = ",".join(level_name(level) for level in ROBUSTNESS_LEVELS)


def levels_value(text: str) -> tuple[float, ...]:
    """``--levels``: comma-separated levels (:func:`~sb3_formation.experiment.robustness.check_levels`), ascending."""
    try:
        levels = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected levels such as 0,0.5,1, got {text!r:.60}") from None
    try:
        return check_levels(levels)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``robustness`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "robustness",
        help="robustness curves: success, contacts and shape error as a disturbance profile's errors grow",
        description="Evaluate each target as the benchmark does (stage 3, fixed held-out seeds, on "
        f"{', '.join(BENCHMARK_SCENES)}) under a disturbance profile scaled by each level (0: ideal, 1: the profile), "
        f"and under each of its parts ({', '.join(PARTS)}) alone; print one table, write it with every evaluation and "
        "a figure of curves per scene set into --out.",
    )
    parser.add_argument("targets", nargs="+", help="run folders, model .zip files or <kind>:<name> targets")
    parser.add_argument(
        "--disturbances",
        type=disturbances_source,
        default="realistic",
        help="the profile scaled: realistic, harsh or a YAML file (docs/disturbances.md; default realistic)",
    )
    parser.add_argument(
        "--levels",
        type=levels_value,
        default=DEFAULT_LEVELS,
        help=f"comma-separated levels in [0, {MAX_LEVEL:g}] that scale every error (default {DEFAULT_LEVELS})",
    )
    parser.add_argument(
        "--no-factors", action="store_true", help="only the parts together, not each part alone (a fifth of the work)"
    )
    parser.add_argument(
        "--episodes", type=episodes_count, default=BENCHMARK_EPISODES, help=f"per point (default {BENCHMARK_EPISODES})"
    )
    parser.add_argument(
        "--seed", type=seed_value, default=BENCHMARK_SEED, help=f"episode k plays seed + k (default {BENCHMARK_SEED})"
    )
    add_scene_sets_option(parser)
    parser.add_argument("--n-envs", type=teams_count, default=16, help="teams played at once (default 16)")
    parser.add_argument("--workers", type=teams_count, default=2, help="processes stepping the teams (default 2)")
    parser.add_argument("--labels", help="comma-separated label per target (default: the targets)")
    parser.add_argument(
        "--out", type=output_path, default=output_path("robustness"), help="a new or empty folder (default robustness/)"
    )
    parser.add_argument("--device", default="auto", help="torch device (default auto)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_recipe_option(parser, "recipe of controller: targets (default ch5-bearing)")
    add_trust_pickle_option(parser)
    parser.set_defaults(run=run)


def starting(args: argparse.Namespace) -> str:
    """The line ``robustness`` starts with."""
    return f"robustness of {', '.join(args.targets)} under {args.disturbances} into {args.out} (Ctrl-C stops it)"


def run(args: argparse.Namespace) -> int:
    """``sb3-formation robustness TARGET...``: the table, the evaluations and the curves, with ``--out`` locked from
    the check that it is new or empty to the last figure (a second sweep into it is refused)."""
    targets = [Target.parse(target).with_recipe(args.recipe) for target in args.targets]
    labels = target_labels(args.labels, targets)
    folders = label_folders(labels)
    check_new_folder(args.out)
    check_robustness_inputs(targets, folders, args.out, args.disturbances, args.levels, not args.no_factors, args.scenes)
    with model_trust(args):
        for target in targets:  # every target loads before any is evaluated
            target.load(args.device)
        with folder_lock(args.out, "robustness folder", remove=True):
            check_new_folder(args.out)  # again, now that no other sweep can start writing here
            rows = run_robustness(
                targets,
                folders,
                args.out,
                disturbances=args.disturbances,
                levels=args.levels,
                factors=not args.no_factors,
                episodes=args.episodes,
                seed=args.seed,
                scenes=args.scenes,
                n_envs=args.n_envs,
                workers=args.workers,
                recipe=args.recipe,
                device=args.device,
                progress_bar=not args.no_progress,
                command=args.command_line,
            )
            from sb3_formation.viz.plots import plot_robustness, save_figures  # matplotlib: only where one is drawn

            cells = [row.cells() for row in rows]
            save_figures(
                {
                    args.out / FIGURES_FOLDER / f"robustness_{scenes}.png": plot_robustness(cells, scenes)
                    for scenes in args.scenes
                }
            )
    print((args.out / TABLE_FILE).read_text().rstrip())
    print(
        f"table written to {args.out / TABLE_FILE} (data: {args.out / RESULTS_FILE}), curves to {args.out / FIGURES_FOLDER}, "
        f"evaluations to {args.out}/<label>/<factor>/<level>/<scenes>/"
    )
    return 0
