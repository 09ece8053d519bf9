"""The ``sb3-formation`` command line: a thin layer over functions a notebook can call with the same names."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import yaml
from PIL import Image

from sb3_formation.env.config import PRESETS, FormationConfig
from sb3_formation.env.episodes import random_policy, run_episode
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.experiment.evaluation import (
    SUMMARY_FILE,
    THESIS_EVALUATION_EPISODES,
    TRAJECTORIES_FILE,
    Trajectories,
    comparison_table,
    evaluate_run,
    model_fingerprint,
)
from sb3_formation.experiment.training import (
    FINAL_MODEL,
    TrainSettings,
    load_settings,
    load_trained,
    reduce_to_overrides,
    resume,
    train,
)
from sb3_formation.utils.files import atomic_write
from sb3_formation.viz.plots import (
    FIGURES,
    plot_error_curves,
    plot_evaluation_bars,
    plot_training_curves,
    plot_trajectory,
    save_figure,
)
from sb3_formation.viz.video import render_episodes


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _iterations(text: str) -> list[int]:
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected three iteration counts A,B,C (stages 1, 2, 3), got {text!r}")
    return values


def _assignment(text: str) -> tuple[str, object]:
    name, separator, value = text.partition("=")
    if not separator or not name:
        raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
    return name.strip(), yaml.safe_load(value)


def _seed(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _indices(text: str) -> list[int]:
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected episode indices such as 0,2,5, got {text!r}")
    return values


def _add_protocol_arguments(parser: argparse.ArgumentParser) -> None:
    """The evaluation protocol's options, shared by ``evaluate`` and ``compare``."""
    parser.add_argument("--episodes", type=_positive_int, help="episodes (thesis: 500 in ch. 4, 200 in ch. 5)")
    parser.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default 3)")
    parser.add_argument("--seed", type=_seed, default=0, help="episode k plays the scenario of seed + k (default 0)")
    parser.add_argument("--n-envs", type=_positive_int, default=8, help="teams played at once (default 8)")
    parser.add_argument("--workers", type=_positive_int, default=1, help="worker processes (default 1)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of using the mean")
    parser.add_argument("--device", default="auto", help="torch device (default auto)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def preset_for(reward: str | None, n_agents: int | None, team_reward: bool) -> str:
    """The thesis preset meant by ``--reward``, ``--agents`` and ``--team-reward``.

    bearing -> ch5-bearing; angle with the team reward -> ch4-team; angle with 3 agents (the default) ->
    ch4-individual; angle with more agents -> ch5-angle; no reward given -> ch5-bearing, or ch4-team with the team
    reward.
    """
    if reward == "bearing":
        return "ch5-bearing"
    if reward == "angle" or team_reward:
        if team_reward:
            return "ch4-team"
        return "ch4-individual" if n_agents in (None, 3) else "ch5-angle"
    return "ch5-bearing"


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
    train.add_argument("--preset", choices=sorted(PRESETS), help="thesis set-up (overrides --reward/--team-reward)")
    train.add_argument("--reward", choices=("angle", "bearing"), help="shape reward: angle (ch. 4/5) or bearing (ch. 5)")
    train.add_argument("--agents", type=int, help="team size n >= 3")
    train.add_argument("--team-reward", action="store_true", default=None, help="every agent gets the team reward")
    train.add_argument(
        "--iterations",
        type=_iterations,
        help="PPO iterations of stages 1,2,3 (thesis: 10000,10000,20000 in ch. 4, 5000,5000,15000 in ch. 5)",
    )
    train.add_argument(
        "--recurrent",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="recurrent actor and critic (default: as in the thesis, on for chapter-5 presets, off for chapter 4)",
    )
    train.add_argument("--cell", choices=("gru", "lstm"), help="recurrent cell (default gru)")
    train.add_argument("--n-envs", type=_positive_int, help="parallel teams (thesis: 12 in ch. 4, 14 in ch. 5)")
    train.add_argument("--workers", type=_positive_int, help="worker processes stepping the teams (default 1)")
    train.add_argument("--seed", type=_seed, help="seed of PPO and of the scenarios (default 0)")
    train.add_argument("--device", help="torch device: auto, cpu, cuda (default auto)")
    train.add_argument("--logdir", help="folder for run folders (default runs/)")
    train.add_argument("--checkpoint-every", type=_positive_int, help="iterations between checkpoints (default 50)")
    train.add_argument("--success-threshold", type=float, help="end stages 1-2 early at this rolling success rate")
    train.add_argument(
        "--env",
        type=_assignment,
        action="append",
        metavar="FIELD=VALUE",
        help="override a FormationConfig field, e.g. --env max_steps=1000 (repeatable)",
    )
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue a run from its latest checkpoint")
    train.add_argument("--run-dir", type=Path, help="write the run into this folder (default: a new one under --logdir)")
    evaluate = commands.add_parser(
        "evaluate",
        help="evaluate a trained policy: success rate with a 95%% interval, errors, episodes.csv, trajectories",
        description="Play fixed-seed episodes (episode k from seed + k) with a trained policy and write "
        "summary.json (success rate with a 95%% Wilson interval; mean and std of errors, steps and collisions), "
        "episodes.csv (one row per episode) and trajectories.npz (every step of the first episodes).",
    )
    evaluate.add_argument("target", type=Path, help="a run folder or a model .zip (normaliser beside it)")
    _add_protocol_arguments(evaluate)
    evaluate.add_argument("--agents", type=int, help="team size (default: the model's; must match it)")
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
    plot.add_argument("targets", type=Path, nargs="+", help="run folders (or eval folders / files for trajectories, errors)")
    plot.add_argument("--out", type=Path, help="figure file; .png (default), .svg or .pdf")
    plot.add_argument("--episodes", type=_indices, help="recorded episodes to draw, e.g. 0,2 (default: all recorded)")
    plot.add_argument("--every", type=_positive_int, default=25, help="steps between formation outlines (default 25)")
    plot.add_argument("--labels", help="comma-separated label per run (runs with the same label are seeds of one curve)")
    plot.add_argument("--window", type=_positive_int, default=100, help="rolling-mean window in iterations (default 100)")
    plot.add_argument("--over", choices=("successful", "all"), default="successful", help="episodes for the bar means")
    render = commands.add_parser(
        "render",
        help="write an MP4 or GIF of evaluation episodes",
        description="Play evaluation episodes with a trained policy and write them as a video, with the step, "
        "success and current errors drawn on each frame. The format follows --out: .mp4 or .gif.",
    )
    render.add_argument("target", type=Path, help="a run folder or a model .zip (normaliser beside it)")
    render.add_argument("--episodes", type=_positive_int, default=1, help="episodes (default 1)")
    render.add_argument("--out", type=Path, help="video file, .mp4 or .gif (default: <run>/eval/episodes.mp4)")
    render.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default 3)")
    render.add_argument("--seed", type=_seed, default=0, help="episode k plays the scenario of seed + k (default 0)")
    render.add_argument("--fps", type=_positive_int, default=20, help="frames per second (default 20)")
    render.add_argument("--frame-every", type=_positive_int, default=1, help="keep every k-th step as a frame")
    render.add_argument("--max-steps", type=_positive_int, help="cut episodes at this many steps (default: the model's)")
    render.add_argument("--stochastic", action="store_true", help="sample actions instead of using the mean")
    render.add_argument("--device", default="auto", help="torch device (default auto)")
    compare = commands.add_parser(
        "compare",
        help="evaluate several runs on the same seeds; print a Markdown table and draw the bar chart",
        description="Evaluate every run on the same fixed-seed episodes (reusing its eval/ when it holds the same "
        "protocol for the same model file), print a Markdown table and write the evaluation bar chart.",
    )
    compare.add_argument("targets", type=Path, nargs="+", help="run folders or model .zip files")
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
    sweep.add_argument("--max-concurrent", type=_positive_int, help="trials at once (default: one per CPU)")
    sweep.add_argument("--logdir", help="folder for the experiment's folder (default: the experiment's logdir)")
    rollout = commands.add_parser(
        "rollout",
        help="play episodes with a random policy, print per-episode metrics and save the final frame",
        description="Play episodes of the formation env with uniformly random actions (a baseline and a smoke test).",
    )
    rollout.add_argument(
        "--preset", choices=sorted(PRESETS), default="ch5-bearing", help="thesis set-up (default: %(default)s)"
    )
    rollout.add_argument("--agents", type=int, default=None, help="team size n >= 3 (default: the preset's)")
    rollout.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default: %(default)s)")
    rollout.add_argument("--episodes", type=_positive_int, default=2, help="number of episodes (default: %(default)s)")
    rollout.add_argument(
        "--max-steps", type=_positive_int, default=None, help="episode length T_s in steps (default: the preset's 2500)"
    )
    rollout.add_argument("--seed", type=int, default=0, help="seed of the first episode; episode k uses seed + k")
    rollout.add_argument("--out", type=Path, default=Path("runs/rollout_final_frame.png"), help="PNG of the final frame")
    rollout.add_argument("--json", action="store_true", help="print the summaries as JSON lines")
    return parser


def rollout_command(args: argparse.Namespace) -> int:
    """``sb3-formation rollout``: random-policy episodes with per-episode metrics and a PNG of the final frame."""
    overrides = {"stage": args.stage}
    if args.agents is not None:
        overrides["n_agents"] = args.agents
    if args.max_steps is not None:
        overrides["max_steps"] = args.max_steps
    config = FormationConfig.preset(args.preset, **overrides)
    env = FormationEnv(config, render_mode="rgb_array")
    policy = random_policy(env, seed=args.seed)
    print(f"{args.preset}: n={config.n_agents}, stage {config.stage}, T_s={config.max_steps}, random policy")
    for episode in range(args.episodes):
        summary = run_episode(env, policy, seed=args.seed + episode)
        if args.json:
            print(json.dumps({"episode": episode, **summary}))
        else:
            print(
                f"episode {episode}: steps={summary['length']} success={summary['success']} "
                f"return={summary['return']:.2f} angle_error={summary['angle_error_deg']:.1f} deg "
                f"bearing_error={summary['bearing_error']:.3f} distance_error={summary['neighbour_distance_error']:.3f} m "
                f"goal_distance={summary['final_goal_distance']:.2f} m "
                f"collisions obstacle/agent={summary['collisions_obstacle']}/{summary['collisions_agent']}"
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(env.render()).save(args.out)
    print(f"final frame saved to {args.out}")
    return 0


def train_settings(args: argparse.Namespace) -> TrainSettings:
    """The settings of ``sb3-formation train``: YAML file first, then the flags given on the command line."""
    values: dict = {}
    if args.config is not None:
        if not args.config.exists():
            raise FileNotFoundError(f"--config: no such file {args.config}")
        try:
            loaded = yaml.safe_load(args.config.read_text()) or {}
        except yaml.YAMLError as error:
            raise ValueError(f"{args.config} is not valid YAML: {error}") from error
        if not isinstance(loaded, dict):
            raise ValueError(f"{args.config} must hold a mapping of settings, not {type(loaded).__name__}")
        values.update(reduce_to_overrides(loaded))
    env = dict(values.get("env") or {})
    if args.preset is not None:
        values["preset"] = args.preset
    elif args.reward is not None or args.team_reward:
        values["preset"] = preset_for(args.reward, args.agents, bool(args.team_reward))
    if args.agents is not None:
        env["n_agents"] = args.agents
    if args.team_reward:
        env["team_reward"] = True
    for name, value in args.env or []:
        env[name] = value
    values["env"] = env
    flags = {
        "iterations": args.iterations,
        "n_envs": args.n_envs,
        "workers": args.workers,
        "seed": args.seed,
        "device": args.device,
        "logdir": args.logdir,
        "checkpoint_every": args.checkpoint_every,
        "success_threshold": args.success_threshold,
        "recurrent": args.recurrent,
        "cell": args.cell,
    }
    values.update({name: value for name, value in flags.items() if value is not None})
    if args.no_progress:
        values["progress_bar"] = False
    return TrainSettings.from_dict(values)


def train_command(args: argparse.Namespace) -> int:
    """``sb3-formation train``: a new run, or ``--resume`` of an existing one."""
    if args.resume is not None:
        given = [
            name
            for name in (
                "config",
                "preset",
                "reward",
                "agents",
                "team_reward",
                "iterations",
                "n_envs",
                "workers",
                "seed",
                "device",
                "logdir",
                "checkpoint_every",
                "success_threshold",
                "recurrent",
                "cell",
                "env",
                "run_dir",
            )
            if getattr(args, name) is not None
        ]
        if given:
            raise ValueError(f"--resume continues a run with its own settings; drop {', '.join('--' + g for g in given)}")
        run_dir = resume(args.resume)
        settings = load_settings(run_dir)
    else:
        settings = train_settings(args)
        policy = f"recurrent ({settings.cell})" if settings.resolved_recurrent() else "MLP"
        print(
            f"training {settings.preset}: n={settings.config().n_agents}, iterations per stage "
            f"{list(settings.resolved_iterations())}, {settings.resolved_n_envs()} teams, {policy} policy"
        )
        run_dir = train(settings, command=args.command_line, run_dir=args.run_dir)
    print(f"run folder: {run_dir}")
    if settings.evaluation is not None and (run_dir / FINAL_MODEL).exists():
        _print_summary(evaluate_run(run_dir, settings.evaluation, progress_bar=settings.progress_bar).summary)
    print(f"tensorboard --logdir {Path(run_dir).parent}")
    return 0


def _run_folder(target: Path) -> Path:
    """The folder of a run (or of a model file)."""
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


def _evaluate_run(args: argparse.Namespace, target: Path, episodes: int | None, out: Path | None = None) -> dict:
    """Evaluate one run with the protocol options of ``args``, save its files, and return its summary."""
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
    result = evaluate_run(target, protocol, device=args.device, progress_bar=not args.no_progress, out=out)
    print(f"{target}: evaluation written to {out or _run_folder(target) / 'eval'}")
    return result.summary


def evaluate_command(args: argparse.Namespace) -> int:
    """``sb3-formation evaluate``: success rate with a Wilson interval, errors, episode table and trajectories."""
    if args.trajectories < 0:
        raise ValueError(f"--trajectories must be >= 0, got {args.trajectories}")
    _print_summary(_evaluate_run(args, args.target, args.episodes, args.out))
    return 0


def _labels(text: str | None, targets: Sequence[Path]) -> list[str]:
    """One label per target: from ``--labels`` (comma-separated) or the folder names."""
    if text is None:
        return [_run_folder(target).name for target in targets]
    labels = [label.strip() for label in text.split(",")]
    if len(labels) != len(targets):
        raise ValueError(f"--labels gives {len(labels)} labels for {len(targets)} runs")
    return labels


def _eval_file(target: Path, name: str) -> Path:
    """``name`` of an evaluation given as the file itself, an eval folder or a run folder."""
    for candidate in (target, target / name, _run_folder(target) / "eval" / name):
        if candidate.is_file() and candidate.name == name:
            return candidate
    raise FileNotFoundError(f"no {name} in {target}: run `sb3-formation evaluate {target}` first")


def _load_summary(target: Path) -> dict:
    path = _eval_file(target, SUMMARY_FILE)
    try:
        summary = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON: {error}") from error
    if not isinstance(summary, dict) or "success_rate" not in summary:
        raise ValueError(f"{path} is not an evaluation summary written by sb3-formation")
    return summary


def plot_command(args: argparse.Namespace) -> int:
    """``sb3-formation plot FIGURE TARGET...``: one of the thesis-style figures, as PNG, SVG or PDF."""
    if args.figure not in FIGURES:
        raise ValueError(f"unknown figure {args.figure!r}: choose one of {', '.join(FIGURES)}")
    if args.figure in ("trajectories", "errors"):
        if len(args.targets) != 1:
            raise ValueError(f"{args.figure} draws one evaluation; got {len(args.targets)} targets")
        path = _eval_file(args.targets[0], TRAJECTORIES_FILE)
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
        summaries = dict(zip(labels, (_load_summary(target) for target in args.targets)))
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
    trained = load_trained(args.target, device=args.device)
    out = args.out or _run_folder(args.target) / "eval" / "episodes.mp4"
    frames = render_episodes(
        trained,
        out,
        episodes=args.episodes,
        stage=args.stage,
        seed=args.seed,
        deterministic=not args.stochastic,
        fps=args.fps,
        frame_every=args.frame_every,
        env_overrides={} if args.max_steps is None else {"max_steps": args.max_steps},
        progress_bar=True,
    )
    print(f"{frames} frames written to {out}")
    return 0


def _matching_summary(target: Path, args: argparse.Namespace, episodes: int | None) -> dict | None:
    """The run's stored evaluation summary if it is of the same model file under the same protocol, else ``None``."""
    try:
        summary = _load_summary(target)
        model = load_trained(target, device="cpu").source
    except (FileNotFoundError, ValueError):
        return None
    protocol = {"stage": args.stage, "seed": args.seed, "deterministic": not args.stochastic}
    if episodes is not None:
        protocol["episodes"] = episodes
    same_model = (summary.get("model") or {}).get("sha256") == model_fingerprint(model)["sha256"]
    return summary if same_model and all(summary.get(key) == value for key, value in protocol.items()) else None


def compare_command(args: argparse.Namespace) -> int:
    """``sb3-formation compare RUN...``: every run on the same seeds, a Markdown table and the bar chart."""
    labels = _labels(args.labels, args.targets)
    if len(set(labels)) != len(labels):
        raise ValueError(f"labels must differ, got {labels}")
    episodes = args.episodes
    if episodes is None:  # the thesis's protocol of the runs' chapter (the larger one if they mix chapters)
        layouts = {load_trained(target, device="cpu").config.layout for target in args.targets}
        episodes = max(THESIS_EVALUATION_EPISODES[layout] for layout in layouts)
    summaries = {}
    for label, target in zip(labels, args.targets):
        summary = None if args.force else _matching_summary(target, args, episodes)
        if summary is not None:
            print(f"{target}: reusing {_eval_file(target, SUMMARY_FILE)}")
        summaries[label] = summary or _evaluate_run(args, target, episodes)
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
    print(f"sweep folder: {result.folder}")
    return 1 if result.failed else 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-formation`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.command_line = shlex.join(["sb3-formation", *argv])
    commands = {
        "rollout": rollout_command,
        "train": train_command,
        "evaluate": evaluate_command,
        "plot": plot_command,
        "render": render_command,
        "compare": compare_command,
        "sweep": sweep_command,
    }
    try:
        return commands[args.command](args)
    except (ValueError, TypeError, OSError, RuntimeError) as error:  # bad input, files, a failed worker: one line
        if args.debug:
            raise
        print(f"sb3-formation: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
