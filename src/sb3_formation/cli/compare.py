"""``sb3-formation compare``: several policies on the same seeds."""

from __future__ import annotations

import argparse

from sb3_formation.cli.common import (
    add_protocol_arguments,
    disturbances_label,
    evaluate_with_protocol,
    model_trust,
    target_labels,
)
from sb3_formation.env.scenes import DEFAULT_SCENES
from sb3_formation.experiment.evaluation import SUMMARY_FILE, stored_summary
from sb3_formation.experiment.reports import comparison_table
from sb3_formation.experiment.sections import EvaluationSection
from sb3_formation.experiment.targets import Target
from sb3_formation.utils.arguments import output_path
from sb3_formation.utils.files import atomic_write


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``compare`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "compare",
        help="evaluate several runs on the same seeds; print a Markdown table and draw the bar chart",
        description="Evaluate every run on the same fixed-seed episodes (reusing its eval/ when it holds the same "
        "protocol for the same model file), print a Markdown table and write the evaluation bar chart.",
    )
    parser.add_argument("targets", nargs="+", help="run folders, model .zip files or <kind>:<name> targets")
    add_protocol_arguments(parser)
    parser.add_argument("--labels", help="comma-separated label per run (default: the run folder names)")
    parser.add_argument("--over", choices=("successful", "all"), default="successful", help="episodes for the means")
    parser.add_argument(
        "--out", type=output_path, default=output_path("compare.png"), help="bar chart file (default compare.png)"
    )
    parser.add_argument("--table", type=output_path, help="also write the Markdown table to this file")
    parser.add_argument("--force", action="store_true", help="evaluate again even if eval/ matches")
    parser.set_defaults(run=run)


def starting(args: argparse.Namespace) -> str:
    """The line ``compare`` starts with."""
    return f"comparing {', '.join(args.targets)} on the same episodes (Ctrl-C stops it)"


def run(args: argparse.Namespace) -> int:
    """``sb3-formation compare TARGET...``: every policy on the same seeds, a Markdown table and the bar chart."""
    with model_trust(args):
        return _compare(args)


def _compare(args: argparse.Namespace) -> int:
    # --recipe is the recipe of the controller: targets; runs and models act in the task they were trained in
    targets = [Target.parse(target).with_recipe(args.recipe) for target in args.targets]
    labels = target_labels(args.labels, targets)
    if len(set(labels)) != len(labels):
        raise ValueError(f"labels must differ, got {labels}")
    from sb3_formation.viz.plots import FIGURE_FORMATS  # matplotlib: only where a figure is drawn

    if args.out.suffix[1:].lower() not in ("", *FIGURE_FORMATS):  # before any evaluation
        raise ValueError(
            f"cannot save a figure as {args.out.suffix[1:]!r} ({args.out}): use one of {', '.join(FIGURE_FORMATS)}"
        )
    for target in targets:  # every target loads before any is evaluated (and written to)
        target.load(args.device)
    # the recipes' protocol (the larger one if they differ, e.g. chapter 4's 500 episodes and chapter 5's 200)
    protocols = [None if recipe is None else recipe.evaluation for recipe in (target.task_recipe() for target in targets)]
    episodes = args.episodes or max((own.episodes for own in protocols if own is not None), default=None)
    if episodes is None:
        raise ValueError(
            "none of the targets belongs to a run folder whose recipe gives the number of episodes: give --episodes"
        )
    protocol = EvaluationSection(
        episodes=episodes,
        stage=args.stage or max((3 if own is None or own.stage is None else own.stage for own in protocols), default=3),
        seed=args.seed,
        n_envs=args.n_envs,
        deterministic=not args.stochastic,
        record=5,
    )
    summaries = {}
    for label, target in zip(labels, targets):
        summary = None if args.force else stored_summary(target, protocol, args.scenes, args.disturbances)
        if summary is not None:
            stored = target.evaluation_file(SUMMARY_FILE, args.scenes or DEFAULT_SCENES, disturbances_label(args))
            print(f"{target}: reusing {stored}")
        summaries[label] = summary or evaluate_with_protocol(args, target, protocol)
    table = comparison_table(summaries, over=args.over)
    print(table)
    if args.table is not None:
        atomic_write(args.table, table + "\n")
        print(f"table written to {args.table}")
    from sb3_formation.viz.plots import plot_evaluation_bars, save_figure  # matplotlib: only where a figure is drawn

    print(f"figure written to {save_figure(plot_evaluation_bars(summaries, over=args.over), args.out)}")
    return 0
