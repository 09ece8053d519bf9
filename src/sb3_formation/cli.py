"""The ``sb3-formation`` command line: a thin layer over functions a notebook can call with the same names."""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

from PIL import Image

from sb3_formation.env.rendering import render_frame
from sb3_formation.env.state import TeamState
from sb3_formation.experiment.evaluation import (
    EVALUATION_TEAMS,
    SUMMARY_FILE,
    TRAJECTORIES_FILE,
    PlayJob,
    Trajectories,
    comparison_table,
    evaluate_target,
    load_summary,
    play_episodes,
    seed_policy,
    stored_summary,
)
from sb3_formation.experiment.export import export_pretrained
from sb3_formation.experiment.pretrained import pretrained_card, pretrained_names
from sb3_formation.experiment.runs import FINAL_MODEL
from sb3_formation.experiment.settings import (
    CLI_CONVERSIONS,
    TrainSettings,
    cli_options,
    layered_settings,
    load_settings,
    positive_int,
    seed_value,
)
from sb3_formation.experiment.setups import DEFAULT_SETUP, load_setup, setup_names, thesis_setup_for
from sb3_formation.experiment.targets import default_protocol, evaluation_file, evaluation_folder, load_policy, target_kind
from sb3_formation.experiment.training import TrainingStopped, resume, train
from sb3_formation.utils.files import atomic_path, atomic_write
from sb3_formation.viz.plots import (
    FIGURES,
    plot_error_curves,
    plot_evaluation_bars,
    plot_training_curves,
    plot_trajectory,
    save_figure,
    save_sweep_curves,
)
from sb3_formation.viz.video import render_episodes

#: Options of ``train`` that are not settings: the YAML file, the thesis's shorthand and the run folder.
TRAIN_ONLY_OPTIONS = ("config", "reward", "agents", "team_reward", "run_dir")


def _indices(text: str) -> list[int]:
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected episode indices such as 0,2,5, got {text!r}")
    return values


TARGET_HELP = (
    "a run folder, a model .zip (normaliser beside it), controller:<name> (e.g. controller:classical) or "
    "pretrained:<name> (a shipped policy: sb3-formation pretrained)"
)
PRESET_HELP = (
    f"set-up of a controller: target (default {DEFAULT_SETUP}); trained models act in the task they were trained in "
    "(pretrained: refuses another)"
)


def _add_protocol_arguments(parser: argparse.ArgumentParser) -> None:
    """The evaluation protocol's options, shared by ``evaluate`` and ``compare``."""
    parser.add_argument("--episodes", type=positive_int, help="episodes (default: the set-up's; thesis: 500 ch. 4, 200 ch. 5)")
    parser.add_argument("--stage", type=int, choices=(1, 2, 3), help="curriculum stage (default: the set-up's, 3)")
    parser.add_argument("--seed", type=seed_value, default=0, help="episode k plays the scenario of seed + k (default 0)")
    parser.add_argument(
        "--n-envs", type=positive_int, default=EVALUATION_TEAMS, help=f"teams played at once (default {EVALUATION_TEAMS})"
    )
    parser.add_argument(
        "--workers", type=positive_int, default=1, help="processes stepping the teams, this one included (default 1)"
    )
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of using the mean")
    parser.add_argument("--device", default="auto", help="torch device (default auto)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--preset", help=PRESET_HELP)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(prog="sb3-formation", description=__doc__)
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    commands = parser.add_subparsers(dest="command", required=True)
    train = commands.add_parser(
        "train",
        help="train a shared PPO policy through the curriculum",
        description="Train one PPO policy shared by every agent through the thesis's three curriculum stages. "
        "Settings come from the preset, then --config FILE.yaml, then the flags given here.",
    )
    train.add_argument("--config", type=Path, help="YAML file with any of the settings below (env: and ppo: sections)")
    train.add_argument("--reward", choices=("angle", "bearing"), help="shape reward: angle (ch. 4/5) or bearing (ch. 5)")
    train.add_argument("--agents", type=int, help="team size n >= 3")
    train.add_argument("--team-reward", action="store_true", default=None, help="every agent gets the team reward")
    for name, options in cli_options():
        options = dict(options)
        train.add_argument(options.pop("flag"), dest=name, default=None, **options)
    train.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue a run from its latest checkpoint")
    train.add_argument(
        "--run-dir", type=Path, help="write the run into this new or empty folder (default: a new one under --logdir)"
    )
    commands.add_parser(
        "presets",
        help="list the set-ups --preset can name",
        description="List the set-ups shipped with the package (a set-up YAML file's path works as --preset too).",
    )
    pretrained = commands.add_parser(
        "pretrained",
        help="list the trained policies shipped with the package (pretrained:<name> targets), or export one",
        description="List the shipped policies with their stored evaluation (the thesis protocol), or with --export "
        "make one of a finished run: its model without optimiser state, its normaliser, settings, a fresh evaluation "
        "of that model file and a card recording the command, seed, wall time and versions.",
    )
    pretrained.add_argument("--export", type=Path, metavar="RUN_DIR", help="a finished run folder to ship")
    pretrained.add_argument("--name", help="name of the exported policy (pretrained:<name>)")
    pretrained.add_argument("--into", type=Path, help="folder of shipped policies (default: the package's)")
    evaluate = commands.add_parser(
        "evaluate",
        help="evaluate a trained policy: success rate with a 95%% interval, errors, episodes.csv, trajectories",
        description="Play fixed-seed episodes (episode k from seed + k) with a trained policy and write "
        "summary.json (success rate with a 95%% Wilson interval; mean and std of errors, steps and collisions), "
        "episodes.csv (one row per episode) and trajectories.npz (every step of the first episodes).",
    )
    evaluate.add_argument("target", help=TARGET_HELP)
    _add_protocol_arguments(evaluate)
    evaluate.add_argument(
        "--agents", type=int, help="team size (default: the model's; another only for one trained on several)"
    )
    evaluate.add_argument(
        "--trajectories", type=int, default=5, metavar="K", help="record every step of the first K episodes (default 5)"
    )
    evaluate.add_argument("--out", type=Path, help="folder for the files (default: <run>/eval)")
    plot = commands.add_parser(
        "plot",
        help="draw thesis-style figures: trajectories, errors, bars, training",
        description="trajectories: paths, obstacles, goal and formation of recorded evaluation episodes (one file per "
        "episode); errors: mean angle and distance error against the step; bars: evaluation errors of one or several "
        "runs side by side; training: episode reward and success rate against the iteration, mean and std over runs.",
    )
    plot.add_argument("figure", help=f"one of {', '.join(FIGURES)}")
    plot.add_argument("targets", nargs="+", help="run folders, <kind>:<name> targets, or eval folders / files")
    plot.add_argument("--out", type=Path, help="figure file; .png (default), .svg or .pdf")
    plot.add_argument("--episodes", type=_indices, help="recorded episodes to draw, e.g. 0,2 (default: all recorded)")
    plot.add_argument("--every", type=positive_int, default=25, help="steps between formation outlines (default 25)")
    plot.add_argument("--labels", help="comma-separated label per run (runs with the same label are seeds of one curve)")
    plot.add_argument("--window", type=positive_int, default=100, help="rolling-mean window in iterations (default 100)")
    plot.add_argument("--over", choices=("successful", "all"), default="successful", help="episodes for the bar means")
    plot.add_argument("--preset", help="set-up of controller: targets (default: " + DEFAULT_SETUP + ")")
    render = commands.add_parser(
        "render",
        help="write an MP4 or GIF of evaluation episodes",
        description="Play evaluation episodes with a trained policy and write them as a video, with the step, "
        "success and current errors drawn on each frame. The format follows --out: .mp4 or .gif.",
    )
    render.add_argument("target", help=TARGET_HELP)
    render.add_argument("--preset", help=PRESET_HELP)
    render.add_argument("--episodes", type=positive_int, default=1, help="episodes (default 1)")
    render.add_argument("--out", type=Path, help="video file, .mp4 or .gif (default: <run>/eval/episodes.mp4)")
    render.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default 3)")
    render.add_argument("--seed", type=seed_value, default=0, help="episode k plays the scenario of seed + k (default 0)")
    render.add_argument("--fps", type=positive_int, default=20, help="frames per second (default 20)")
    render.add_argument("--frame-every", type=positive_int, default=1, help="keep every k-th step as a frame")
    render.add_argument("--max-steps", type=positive_int, help="cut episodes at this many steps (default: the model's)")
    render.add_argument("--agents", type=int, help="team size (default: the model's; another only for one trained on several)")
    render.add_argument("--stochastic", action="store_true", help="sample actions instead of using the mean")
    render.add_argument("--device", default="auto", help="torch device (default auto)")
    compare = commands.add_parser(
        "compare",
        help="evaluate several runs on the same seeds; print a Markdown table and draw the bar chart",
        description="Evaluate every run on the same fixed-seed episodes (reusing its eval/ when it holds the same "
        "protocol for the same model file), print a Markdown table and write the evaluation bar chart.",
    )
    compare.add_argument("targets", nargs="+", help="run folders, model .zip files or <kind>:<name> targets")
    _add_protocol_arguments(compare)
    compare.add_argument("--labels", help="comma-separated label per run (default: the run folder names)")
    compare.add_argument("--over", choices=("successful", "all"), default="successful", help="episodes for the means")
    compare.add_argument("--out", type=Path, default=Path("compare.png"), help="bar chart file (default compare.png)")
    compare.add_argument("--table", type=Path, help="also write the Markdown table to this file")
    compare.add_argument("--force", action="store_true", help="evaluate again even if eval/ matches")
    sweep = commands.add_parser(
        "sweep",
        help="train and evaluate every seed of an experiment on Ray, then aggregate over the seeds",
        description="Run every seed of an experiment YAML as a Ray task (this machine, or a cluster with --address); "
        "each writes <logdir>/<experiment>/seed_<s>/, a normal run folder. Finished trials are skipped and "
        "interrupted ones resumed when the sweep is started again. Needs pip install 'sb3-formation[ray]'.",
    )
    sweep.add_argument("experiment", type=Path, help="experiment YAML, e.g. experiments/quick-ch5-bearing.yaml")
    sweep.add_argument("--seeds", type=_indices, help="comma-separated seeds (default: the experiment's)")
    sweep.add_argument("--address", help="address of a running Ray cluster (default: start Ray on this machine)")
    sweep.add_argument("--max-concurrent", type=positive_int, help="trials at once (default: one per CPU)")
    sweep.add_argument("--logdir", help="folder for the experiment's folder (default: the experiment's logdir)")
    rollout = commands.add_parser(
        "rollout",
        help="play episodes (random actions by default), print per-episode metrics and save the final frame",
        description="Play episodes of the formation env with a policy (by default controller:random, uniformly random "
        "actions: a baseline and a smoke test), print each episode's metrics and save the last frame as a PNG.",
    )
    rollout.add_argument("target", nargs="?", default="controller:random", help=TARGET_HELP + " (default: %(default)s)")
    rollout.add_argument("--preset", help=f"set-up of a controller: target (default: {DEFAULT_SETUP})")
    rollout.add_argument("--agents", type=int, default=None, help="team size n >= 3 (default: the preset's)")
    rollout.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default: %(default)s)")
    rollout.add_argument("--episodes", type=positive_int, default=2, help="number of episodes (default: %(default)s)")
    rollout.add_argument(
        "--max-steps", type=positive_int, default=None, help="episode length T_s in steps (default: the preset's 2500)"
    )
    rollout.add_argument("--seed", type=int, default=0, help="seed of the first episode; episode k uses seed + k")
    rollout.add_argument("--out", type=Path, default=Path("runs/rollout_final_frame.png"), help="PNG of the final frame")
    rollout.add_argument("--json", action="store_true", help="print the summaries as JSON lines")
    rollout.add_argument("--stochastic", action="store_true", help="sample a trained policy's actions")
    return parser


def rollout_command(args: argparse.Namespace) -> int:
    """``sb3-formation rollout``: episodes of any policy with per-episode metrics and a PNG of the final frame."""
    policy = load_policy(args.target, args.preset, device="cpu")
    overrides = {"stage": args.stage}
    if args.agents is not None:
        overrides["n_agents"] = args.agents
    if args.max_steps is not None:
        overrides["max_steps"] = args.max_steps
    config = policy.config.replace(**overrides)
    job = PlayJob(policy.fit(config), config, args.seed, list(range(args.episodes)), 1, not args.stochastic, 0)
    last: list[TeamState] = []

    def keep(state: TeamState, episode: int) -> None:
        last[:] = [state]

    seed_policy(job.policy, args.seed)
    rows, _ = play_episodes(job, on_step=keep)
    print(f"{args.target}: n={config.n_agents}, stage {config.stage}, T_s={config.max_steps}")
    for summary in rows:
        if args.json:
            print(json.dumps({key: value for key, value in summary.items() if not key.startswith("reward_")}))
        else:
            print(
                f"episode {summary['episode']}: steps={summary['length']} success={summary['success']} "
                f"return={summary['return']:.2f} angle_error={summary['angle_error_deg']:.1f} deg "
                f"bearing_error={summary['bearing_error']:.3f} distance_error={summary['neighbour_distance_error']:.3f} m "
                f"goal_distance={summary['final_goal_distance']:.2f} m "
                f"collisions obstacle/agent={summary['collisions_obstacle']}/{summary['collisions_agent']}"
            )
    with atomic_path(args.out) as temporary:
        Image.fromarray(render_frame(last[0], config)).save(temporary, format="PNG")
    print(f"final frame saved to {args.out}")
    return 0


def train_settings(args: argparse.Namespace) -> TrainSettings:
    """The settings of ``sb3-formation train``: the set-up, then the YAML file, then the flags given."""
    flags = {name: getattr(args, name) for name, _ in cli_options()}
    flags = {name: CLI_CONVERSIONS.get(name, lambda value: value)(value) for name, value in flags.items() if value is not None}
    env = flags.setdefault("env", {})
    if flags.get("preset") is None and (args.reward is not None or args.team_reward):
        flags["preset"] = thesis_setup_for(args.reward, args.agents, bool(args.team_reward))
    if args.agents is not None:
        env["n_agents"] = args.agents
    if args.team_reward:
        env["team_reward"] = True
    return layered_settings(args.config, **flags)


def train_command(args: argparse.Namespace) -> int:
    """``sb3-formation train``: a new run, or ``--resume`` of an existing one."""
    if args.resume is not None:
        given = [
            name for name in (*TRAIN_ONLY_OPTIONS, *(name for name, _ in cli_options())) if getattr(args, name) is not None
        ]
        if given:
            flags = ", ".join("--" + name.replace("_", "-") for name in given)
            raise ValueError(f"--resume continues a run with its own settings; drop {flags}")
        run_dir = resume(args.resume)
        settings = load_settings(run_dir)
    else:
        settings = train_settings(args)
        cell = settings.ppo_kwargs()["policy_kwargs"].get("cell")
        policy = f"recurrent ({cell})" if settings.resolved_recurrent() else "MLP"
        shares = settings.stage_time_shares()
        if shares is None:
            counts = ["until the time is up" if count is None else str(count) for count in settings.resolved_iterations()]
            stages = f"iterations per stage [{', '.join(counts)}]"
        else:
            stages = f"stages 1, 2 end at {shares[0]:.0%}, {shares[1]:.0%} of the time, stage 3 until the time is up"
        budget = "" if settings.minutes is None else f", at most {settings.minutes:g} min"
        print(
            f"training {settings.preset}: n={'/'.join(map(str, settings.resolved_team_sizes()))}, {stages}{budget}, "
            f"{settings.resolved_n_envs()} teams, {policy} policy"
        )
        run_dir = train(settings, command=args.command_line, run_dir=args.run_dir)
    print(f"run folder: {run_dir}")
    if settings.evaluation is not None and (run_dir / FINAL_MODEL).exists():
        _print_summary(evaluate_target(run_dir, settings.evaluation, progress_bar=settings.progress_bar).summary)
    print(f"tensorboard --logdir {Path(run_dir).parent}")
    return 0


def presets_command(args: argparse.Namespace) -> int:
    """``sb3-formation presets``: the shipped set-ups, one line each."""
    names = setup_names()
    width = max(len(name) for name in names)
    for name in names:
        print(f"{name:<{width}}  {load_setup(name).description}")
    return 0


def pretrained_command(args: argparse.Namespace) -> int:
    """``sb3-formation pretrained``: the shipped policies with their stored figures, or ``--export`` of a run."""
    if args.export is not None or args.name is not None or args.into is not None:
        if args.export is None or args.name is None:
            raise ValueError("--export RUN_DIR and --name NAME go together")
        options = {} if args.into is None else {"root": args.into}
        folder = export_pretrained(args.export, args.name, command=args.command_line, progress_bar=True, **options)
        print(f"pretrained:{args.name} written to {folder}")
        card = pretrained_card(args.name, folder.parent)
        _print_summary(card["summary"])
        return 0
    columns = "target | set-up | n | success (95 % CI) | angle error (deg) | bearing error | agent contacts | steps | training"
    print(f"| {columns} |\n|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in pretrained_names():
        card = pretrained_card(name)
        summary = card["summary"]
        low, high = summary["success_rate_ci95"]
        means = {key: value["mean"] for key, value in summary["successful_episodes"].items()}
        contacts = summary["all_episodes"]["collisions_agent"]["mean"]
        sizes = card.get("team_sizes", [card["n_agents"]])
        n = f"{card['n_agents']} (trained on {', '.join(map(str, sizes))})" if len(sizes) > 1 else card["n_agents"]
        print(
            f"| pretrained:{name} | {card['setup']} | {n} | {summary['success_rate']:.1%} "
            f"({low:.1%}-{high:.1%}) | {means['angle_error_deg']:.2f} | {means['bearing_error']:.4f} | {contacts:.3g} | "
            f"{means['length']:.0f} | {card['training_seconds'] / 60:.1f} min |"
        )
    return 0


def _run_folder(target: str | Path) -> Path:
    """The folder of a run (or of a model file)."""
    target = Path(target)
    return target if target.is_dir() else target.parent


def _print_summary(summary: dict) -> None:
    low, high = summary["success_rate_ci95"]
    print(
        f"{summary['episodes']} episodes (stage {summary['stage']}, seed {summary['seed']}): success rate "
        f"{summary['success_rate']:.1%} (95% CI {low:.1%} - {high:.1%})"
    )
    successful, everything = summary["successful_episodes"], summary["all_episodes"]
    print(f"  {'mean ± std over':<26}{'successful episodes':>24}{'all episodes':>24}")
    for name, statistics in everything.items():
        mine = successful[name]
        cell = "-" if mine["mean"] is None else f"{mine['mean']:.3f} ± {mine['std']:.3f}"
        print(f"  {name:<26}{cell:>24}{statistics['mean']:>15.3f} ± {statistics['std']:.3f}")


def _evaluate(args: argparse.Namespace, target: str, episodes: int | None, out: Path | None = None) -> dict:
    """Evaluate one target with the protocol options of ``args``, save its files, and return its summary."""
    protocol = {
        "episodes": episodes,
        "stage": args.stage,
        "seed": args.seed,
        "n_envs": args.n_envs,
        "workers": min(args.workers, args.n_envs),
        "deterministic": not args.stochastic,
        "record": getattr(args, "trajectories", 5),
        "env_overrides": {} if getattr(args, "agents", None) is None else {"n_agents": args.agents},
    }
    out = out or evaluation_folder(target, args.preset)
    result = evaluate_target(target, protocol, args.preset, device=args.device, progress_bar=not args.no_progress, out=out)
    print(f"{target}: evaluation written to {out}")
    return result.summary


def evaluate_command(args: argparse.Namespace) -> int:
    """``sb3-formation evaluate``: success rate with a Wilson interval, errors, episode table and trajectories."""
    if args.trajectories < 0:
        raise ValueError(f"--trajectories must be >= 0, got {args.trajectories}")
    _print_summary(_evaluate(args, args.target, args.episodes, args.out))
    return 0


def _labels(text: str | None, targets: Sequence[str | Path]) -> list[str]:
    """One label per target: from ``--labels`` (comma-separated), else the run folder's name or the target itself."""
    if text is None:
        return [str(target) if target_kind(target) else _run_folder(target).name for target in targets]
    labels = [label.strip() for label in text.split(",")]
    if len(labels) != len(targets):
        raise ValueError(f"--labels gives {len(labels)} labels for {len(targets)} runs")
    return labels


def plot_command(args: argparse.Namespace) -> int:
    """``sb3-formation plot FIGURE TARGET...``: one of the thesis-style figures, as PNG, SVG or PDF."""
    if args.figure not in FIGURES:
        raise ValueError(f"unknown figure {args.figure!r}: choose one of {', '.join(FIGURES)}")
    if args.figure in ("trajectories", "errors"):
        if len(args.targets) != 1:
            raise ValueError(f"{args.figure} draws one evaluation; got {len(args.targets)} targets")
        path = evaluation_file(args.targets[0], TRAJECTORIES_FILE, args.preset)
        trajectories = Trajectories.load(path)
        indices = _recorded_indices(trajectories, args.episodes)
        default = path.parent / "figures" / ("trajectory.png" if args.figure == "trajectories" else "errors.png")
        out = args.out or default
        if args.figure == "errors":
            written = [save_figure(plot_error_curves(trajectories, indices), out)]
        else:
            written = [
                save_figure(
                    plot_trajectory(trajectories, index, every=args.every),
                    out.with_name(f"{out.stem}_{int(trajectories.episodes[index]):03d}{out.suffix or '.png'}"),
                )
                for index in indices
            ]
    elif args.figure == "bars":
        labels = _labels(args.labels, args.targets)
        summaries = dict(zip(labels, (load_summary(target, args.preset) for target in args.targets)))
        written = [save_figure(plot_evaluation_bars(summaries, over=args.over), args.out or Path("evaluation_bars.png"))]
    else:
        labels = _labels(args.labels, args.targets) if args.labels else [_setup_label(t) for t in args.targets]
        groups: dict[str, list[Path]] = {}
        for label, target in zip(labels, args.targets):
            groups.setdefault(label, []).append(target)
        figure = plot_training_curves(groups, window=args.window)
        written = [save_figure(figure, args.out or Path("training_curves.png"))]
    for path in written:
        print(f"figure written to {path}")
    return 0


def _recorded_indices(trajectories: Trajectories, episodes: list[int] | None) -> list[int]:
    """Positions in ``trajectories`` of the requested evaluation episodes (all recorded ones by default)."""
    recorded = trajectories.episodes.tolist()
    if episodes is None:
        return list(range(len(recorded)))
    missing = [episode for episode in episodes if episode not in recorded]
    if missing:
        raise ValueError(f"episodes {missing} were not recorded; recorded episodes: {recorded}")
    return [recorded.index(episode) for episode in episodes]


def _setup_label(run_dir: Path) -> str:
    """A training-curve label naming a run's set-up (preset and team size), so seeds of one set-up share it."""
    settings = load_settings(run_dir)
    return f"{settings.preset} ({settings.config().n_agents} agents)"


def render_command(args: argparse.Namespace) -> int:
    """``sb3-formation render``: a video of evaluation episodes."""
    policy = load_policy(args.target, args.preset, device=args.device)
    out = args.out or evaluation_folder(args.target, args.preset) / "episodes.mp4"
    frames = render_episodes(
        policy,
        out,
        episodes=args.episodes,
        stage=args.stage,
        seed=args.seed,
        deterministic=not args.stochastic,
        fps=args.fps,
        frame_every=args.frame_every,
        env_overrides={
            name: value for name, value in (("max_steps", args.max_steps), ("n_agents", args.agents)) if value is not None
        },
        progress_bar=True,
    )
    print(f"{frames} frames written to {out}")
    return 0


def compare_command(args: argparse.Namespace) -> int:
    """``sb3-formation compare TARGET...``: every policy on the same seeds, a Markdown table and the bar chart."""
    labels = _labels(args.labels, args.targets)
    if len(set(labels)) != len(labels):
        raise ValueError(f"labels must differ, got {labels}")
    # --preset is the set-up of the controller: targets; runs and models act in the task they were trained in
    presets = [args.preset if target_kind(target) else None for target in args.targets]
    for target, preset in zip(args.targets, presets):  # every target loads before any is evaluated (and written to)
        load_policy(target, preset, args.device)
    protocols = [default_protocol(target, args.preset) for target in args.targets]
    protocol = {
        # the set-ups' protocol (the larger one if they differ, e.g. chapter 4's 500 episodes and chapter 5's 200)
        "episodes": args.episodes or max((p["episodes"] for p in protocols if "episodes" in p), default=None),
        "stage": args.stage or max((p.get("stage", 3) for p in protocols), default=3),
    }
    if protocol["episodes"] is None:
        raise ValueError(
            "none of the targets belongs to a run folder whose set-up gives the number of episodes: give --episodes"
        )
    summaries = {}
    for label, target, preset in zip(labels, args.targets, presets):
        own = argparse.Namespace(**{**vars(args), "preset": preset})
        wanted = {**protocol, "seed": args.seed, "deterministic": not args.stochastic}
        summary = None if args.force else stored_summary(target, wanted, own.preset)
        if summary is not None:
            print(f"{target}: reusing {evaluation_file(target, SUMMARY_FILE, own.preset)}")
        own.stage = protocol["stage"]
        summaries[label] = summary or _evaluate(own, target, protocol["episodes"])
    table = comparison_table(summaries, over=args.over)
    print(table)
    if args.table is not None:
        atomic_write(args.table, table + "\n")
        print(f"table written to {args.table}")
    print(f"figure written to {save_figure(plot_evaluation_bars(summaries, over=args.over), args.out)}")
    return 0


def sweep_command(args: argparse.Namespace) -> int:
    """``sb3-formation sweep``: every (configuration x seed) trial on Ray; exit code 1 if a trial failed."""
    try:
        from sb3_formation.experiment.sweep import sweep
    except ImportError as error:  # pragma: no cover - without the extra
        raise ValueError(f"sweep needs Ray: pip install 'sb3-formation[ray]' ({error})") from error
    options = {"seeds": args.seeds, "address": args.address, "max_concurrent": args.max_concurrent, "logdir": args.logdir}
    try:
        result = sweep(args.experiment, **options)
    except KeyboardInterrupt:
        print("sb3-formation: sweep interrupted; run the same command again to finish it", file=sys.stderr)
        return 130
    for seed, error in result.failed.items():
        print(f"sb3-formation: trial seed {seed} failed: {error}", file=sys.stderr)
    curves = save_sweep_curves(result)
    if curves is not None:
        print(f"training curves: {curves}")
    print(f"sweep folder: {result.folder}")
    return 1 if result.failed else 0


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
    commands = {
        "rollout": rollout_command,
        "train": train_command,
        "evaluate": evaluate_command,
        "plot": plot_command,
        "render": render_command,
        "compare": compare_command,
        "sweep": sweep_command,
        "presets": presets_command,
        "pretrained": pretrained_command,
    }
    try:
        return commands[args.command](args)
    except TrainingStopped as stop:
        print(f"sb3-formation: {stop}", file=sys.stderr)
        return 128 + stop.signal_number
    except (ValueError, TypeError, OSError, RuntimeError) as error:  # bad input, files, a failed worker: one line
        if args.debug:
            raise
        print(f"sb3-formation: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
