"""``sb3-formation plot``: thesis-style figures."""

from __future__ import annotations

import argparse
from pathlib import Path

from sb3_formation.cli.common import add_recipe_option, add_scenes_option, indices, steps_count, target_labels
from sb3_formation.env.scenes import DEFAULT_SCENES
from sb3_formation.experiment.evaluation import TRAJECTORIES_FILE, load_summary, load_trajectories
from sb3_formation.experiment.recipes import DEFAULT_RECIPE, load_settings
from sb3_formation.experiment.targets import Target
from sb3_formation.experiment.trajectories import Trajectories
from sb3_formation.utils.arguments import count, output_path

#: The figures ``plot`` draws.
FIGURES = ("trajectories", "errors", "bars", "training")
#: The widest rolling mean of ``plot training`` (``--window``), in iterations.
MAX_WINDOW = 1_000_000


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``plot`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "plot",
        help="draw thesis-style figures: trajectories, errors, bars, training",
        description="trajectories: paths, obstacles, goal and formation of recorded evaluation episodes (one file per "
        "episode); errors: mean angle and distance error against the step; bars: evaluation errors of one or several "
        "runs side by side; training: episode reward and success rate against the iteration, mean and std over runs.",
    )
    parser.add_argument("figure", help=f"one of {', '.join(FIGURES)}")
    parser.add_argument("targets", nargs="+", help="run folders, <kind>:<name> targets, or eval folders / files")
    parser.add_argument("--out", type=output_path, help="figure file; .png (default), .svg or .pdf")
    parser.add_argument("--episodes", type=indices, help="recorded episodes to draw, e.g. 0,2 (default: all recorded)")
    parser.add_argument("--every", type=steps_count, default=25, help="steps between formation outlines (default 25)")
    parser.add_argument("--labels", help="comma-separated label per run (runs with the same label are seeds of one curve)")
    parser.add_argument(
        "--window",
        type=count(MAX_WINDOW),
        default=100,
        help=f"rolling-mean window in iterations, at most {MAX_WINDOW:,} (default 100)",
    )
    parser.add_argument("--over", choices=("successful", "all"), default="successful", help="episodes for the bar means")
    add_recipe_option(parser, "recipe of controller: targets (default: " + DEFAULT_RECIPE + ")")
    add_scenes_option(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """``sb3-formation plot FIGURE TARGET...``: one of the thesis-style figures, as PNG, SVG or PDF."""
    if args.figure not in FIGURES:
        raise ValueError(f"unknown figure {args.figure!r}: choose one of {', '.join(FIGURES)}")
    # matplotlib is imported by the commands that draw, not by every command
    from sb3_formation.viz.plots import (
        plot_error_curves,
        plot_evaluation_bars,
        plot_training_curves,
        plot_trajectory,
        save_figure,
        save_figures,
    )

    if args.figure in ("trajectories", "errors"):
        if len(args.targets) != 1:
            raise ValueError(f"{args.figure} draws one evaluation; got {len(args.targets)} targets")
        target = Target.parse(args.targets[0]).with_recipe(args.recipe)
        path = target.evaluation_file(TRAJECTORIES_FILE, args.scenes or DEFAULT_SCENES)
        trajectories = load_trajectories(path)
        indices = _recordedindices(trajectories, args.episodes)
        default = path.parent / "figures" / ("trajectory.png" if args.figure == "trajectories" else "errors.png")
        out = args.out or default
        if args.figure == "errors":
            written = [save_figure(plot_error_curves(trajectories, indices), out)]
        else:
            written = save_figures(
                {
                    out.with_name(f"{out.stem}_{int(trajectories.episodes[index]):03d}{out.suffix or '.png'}"): (
                        plot_trajectory(trajectories, index, every=args.every)
                    )
                    for index in indices
                }
            )
    elif args.figure == "bars":
        targets = [Target.parse(target).with_recipe(args.recipe) for target in args.targets]
        summaries = dict(zip(target_labels(args.labels, targets), map(load_summary, targets)))
        written = [save_figure(plot_evaluation_bars(summaries, over=args.over), args.out or Path("evaluation_bars.png"))]
    else:
        runs = [Path(run) for run in args.targets]  # run folders
        labels = target_labels(args.labels, list(map(Target.parse, runs))) if args.labels else list(map(_recipe_label, runs))
        groups: dict[str, list[Path]] = {}
        for label, run in zip(labels, runs):
            groups.setdefault(label, []).append(run)
        figure = plot_training_curves(groups, window=args.window)
        written = [save_figure(figure, args.out or Path("training_curves.png"))]
    for path in written:
        print(f"figure written to {path}")
    return 0


def _recordedindices(trajectories: Trajectories, episodes: list[int] | None) -> list[int]:
    """Positions in ``trajectories`` of the requested evaluation episodes (all recorded ones by default)."""
    recorded = trajectories.episodes.tolist()
    if episodes is None:
        return list(range(len(recorded)))
    missing = [episode for episode in episodes if episode not in recorded]
    if missing:
        raise ValueError(f"episodes {missing} were not recorded; recorded episodes: {recorded}")
    return [recorded.index(episode) for episode in episodes]


def _recipe_label(run_dir: Path) -> str:
    """A training-curve label naming a run's recipe (recipe and team size), so seeds of one recipe share it."""
    settings = load_settings(run_dir)
    return f"{settings.recipe.name} ({settings.recipe.config().n_agents} agents)"
