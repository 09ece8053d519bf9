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

from .config import PRESETS, FormationConfig
from .env import FormationEnv
from .evaluation import evaluate
from .rollout import random_policy, run_episode
from .training import TrainSettings, atomic_write_text, load_trained, reduce_to_overrides, resume, train

#: Thesis evaluation sizes: 500 episodes in chapter 4 (thesis 4.4), 200 in chapter 5 (thesis 5.4), by layout.
THESIS_EVALUATION_EPISODES = {"ch4": 500, "ch5": 200}


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
    train.add_argument("--n-envs", type=_positive_int, help="parallel teams (thesis: 12 in ch. 4, 14 in ch. 5)")
    train.add_argument("--workers", type=_positive_int, help="worker processes stepping the teams (default 1)")
    train.add_argument("--seed", type=int, help="seed of PPO and of the scenarios (default 0)")
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
    evaluate = commands.add_parser(
        "evaluate",
        help="evaluate a trained policy: success rate with a 95%% interval and errors",
        description="Play fixed-seed episodes with a trained policy and report the success rate (95%% Wilson "
        "interval) and, over successful episodes, the mean errors and collisions.",
    )
    evaluate.add_argument("target", type=Path, help="a run folder or a model .zip (normaliser beside it)")
    evaluate.add_argument("--episodes", type=_positive_int, help="episodes (thesis: 500 in ch. 4, 200 in ch. 5)")
    evaluate.add_argument("--stage", type=int, choices=(1, 2, 3), default=3, help="curriculum stage (default 3)")
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the scenarios (default 0)")
    evaluate.add_argument("--n-envs", type=_positive_int, default=8, help="teams played in parallel (default 8)")
    evaluate.add_argument("--agents", type=int, help="team size (default: the model's; must match it)")
    evaluate.add_argument("--stochastic", action="store_true", help="sample actions instead of using the mean")
    evaluate.add_argument("--device", default="auto", help="torch device (default auto)")
    evaluate.add_argument("--out", type=Path, help="JSON file (default: <run>/eval/summary.json)")
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
                "env",
            )
            if getattr(args, name) not in (None, False)
        ]
        if given:
            raise ValueError(f"--resume continues a run with its own settings; drop {', '.join('--' + g for g in given)}")
        run_dir = resume(args.resume)
    else:
        settings = train_settings(args)
        print(
            f"training {settings.preset}: n={settings.config().n_agents}, iterations per stage "
            f"{list(settings.resolved_iterations())}, {settings.resolved_n_envs()} teams"
        )
        run_dir = train(settings, command=args.command_line)
    print(f"run folder: {run_dir}")
    print(f"tensorboard --logdir {Path(run_dir).parent}")
    return 0


def evaluate_command(args: argparse.Namespace) -> int:
    """``sb3-formation evaluate``: success rate with a Wilson interval and errors over successful episodes."""
    trained = load_trained(args.target, device=args.device)
    episodes = args.episodes or THESIS_EVALUATION_EPISODES[trained.config.layout]
    overrides = {} if args.agents is None else {"n_agents": args.agents}
    result = evaluate(
        trained,
        episodes,
        stage=args.stage,
        seed=args.seed,
        n_envs=args.n_envs,
        deterministic=not args.stochastic,
        env_overrides=overrides,
    )
    summary = result.summary
    low, high = summary["success_rate_ci95"]
    print(
        f"{summary['episodes']} episodes (stage {summary['stage']}, seed {summary['seed']}): success rate "
        f"{summary['success_rate']:.1%} (95% CI {low:.1%} - {high:.1%})"
    )
    successful, everything = summary["successful_episode_means"], summary["all_episode_means"]
    print(f"  {'mean over':<28}{'successful episodes':>22}{'all episodes':>16}")
    for name in everything:
        value = successful[name]
        print(f"  {name:<28}{'-' if value is None else f'{value:.3f}':>22}{everything[name]:>16.3f}")
    out = args.out
    if out is None:
        base = args.target if args.target.is_dir() else args.target.parent
        out = base / "eval" / "summary.json"
    atomic_write_text(out, json.dumps(summary, indent=2))
    print(f"summary written to {out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``sb3-formation`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.command_line = shlex.join(["sb3-formation", *argv])
    commands = {"rollout": rollout_command, "train": train_command, "evaluate": evaluate_command}
    try:
        return commands[args.command](args)
    except (ValueError, TypeError, OSError) as error:  # bad input or files: one line naming the problem
        if args.debug:
            raise
        print(f"sb3-formation: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
