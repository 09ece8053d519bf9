"""``sb3-formation train``: train a shared PPO policy through the curriculum, or resume a run."""

from __future__ import annotations

import argparse
from pathlib import Path

from sb3_formation.cli.common import RenamedFlag, print_summary
from sb3_formation.experiment.evaluation import evaluate_target
from sb3_formation.experiment.recipes import thesis_recipe_for
from sb3_formation.experiment.runs import FINAL_MODEL
from sb3_formation.experiment.settings import CLI_CONVERSIONS, TrainSettings, cli_options, layered_settings, load_settings
from sb3_formation.experiment.training import resume, train

#: Options of ``train`` that are not settings: the YAML file, the thesis's shorthand and the run folder.
TRAIN_ONLY_OPTIONS = ("config", "reward", "agents", "team_reward", "run_dir")


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``train`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "train",
        help="train a shared PPO policy through the curriculum",
        description="Train one PPO policy shared by every agent through the thesis's three curriculum stages. "
        "Settings come from the recipe, then --config FILE.yaml, then the flags given here.",
    )
    parser.add_argument("--config", type=Path, help="YAML file with any of the settings below (env: and ppo: sections)")
    parser.add_argument("--reward", choices=("angle", "bearing"), help="shape reward: angle (ch. 4/5) or bearing (ch. 5)")
    parser.add_argument("--agents", type=int, help="team size n >= 3")
    parser.add_argument("--team-reward", action="store_true", default=None, help="every agent gets the team reward")
    for name, options in cli_options():
        options = dict(options)
        parser.add_argument(options.pop("flag"), dest=name, default=None, **options)
    parser.add_argument("--preset", dest="recipe", action=RenamedFlag, new="--recipe", help=argparse.SUPPRESS)
    parser.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue a run from its latest checkpoint")
    parser.add_argument(
        "--run-dir", type=Path, help="write the run into this new or empty folder (default: a new one under --logdir)"
    )
    parser.set_defaults(run=run)


def settings_of(args: argparse.Namespace) -> TrainSettings:
    """The settings of ``sb3-formation train``: the recipe, then the YAML file, then the flags given."""
    flags = {name: getattr(args, name) for name, _ in cli_options()}
    flags = {name: CLI_CONVERSIONS.get(name, lambda value: value)(value) for name, value in flags.items() if value is not None}
    env = flags.setdefault("env", {})
    if flags.get("recipe") is None and (args.reward is not None or args.team_reward):
        flags["recipe"] = thesis_recipe_for(args.reward, args.agents, bool(args.team_reward))
    if args.agents is not None:
        env["n_agents"] = args.agents
    if args.team_reward:
        env["team_reward"] = True
    return layered_settings(args.config, **flags)


def run(args: argparse.Namespace) -> int:
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
        settings = settings_of(args)
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
            f"training {settings.recipe}: n={'/'.join(map(str, settings.resolved_team_sizes()))}, {stages}{budget}, "
            f"{settings.resolved_n_envs()} teams, {policy} policy"
        )
        run_dir = train(settings, command=args.command_line, run_dir=args.run_dir)
    print(f"run folder: {run_dir}")
    if settings.evaluation is not None and (run_dir / FINAL_MODEL).exists():
        print_summary(evaluate_target(run_dir, settings.evaluation, progress_bar=settings.progress_bar).summary)
    print(f"tensorboard --logdir {Path(run_dir).parent}")
    return 0
