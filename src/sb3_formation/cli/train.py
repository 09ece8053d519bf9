"""``sb3-formation train``: train a shared PPO policy through the curriculum, or resume a run."""

from __future__ import annotations

import argparse
from pathlib import Path

from sb3_formation.cli.common import (
    RenamedFlag,
    add_scenes_option,
    add_trust_pickle_option,
    assignment,
    positive_float,
    positive_int,
    print_summary,
    seed_value,
    stage_iterations,
)
from sb3_formation.experiment.evaluation import evaluate_target
from sb3_formation.experiment.recipes import thesis_recipe_for
from sb3_formation.experiment.runs import FINAL_MODEL
from sb3_formation.experiment.settings import TrainSettings, layered_settings, load_settings
from sb3_formation.experiment.training import resume, train

#: The options that change the recipe (``recipe_changes``), with their argparse options.
RECIPE_FLAGS: dict[str, dict] = {
    "iterations": dict(
        type=stage_iterations, metavar="A,B,C", help="PPO iterations of stages 1,2,3 (with a budget: their proportions)"
    ),
    "n_envs": dict(type=positive_int, help="parallel teams"),
    "success_threshold": dict(type=float, help="end stages 1-2 early at this rolling success rate"),
    "recurrent": dict(action=argparse.BooleanOptionalAction, help="recurrent actor and critic"),
    "cell": dict(choices=("gru", "lstm"), help="recurrent cell"),
    "steps": dict(type=positive_int, help="budget in agent-steps"),
    "minutes": dict(type=positive_float, help="budget in minutes of training wall-clock (replaces a steps budget)"),
    "normalize_reward": dict(action=argparse.BooleanOptionalAction, help="normalise rewards by a running return std"),
    "eval_every": dict(type=positive_int, help="evaluate every K iterations, keep best_model.zip"),
}
#: The run options (:class:`~sb3_formation.experiment.settings.RunOptions`), with their argparse options.
RUN_FLAGS: dict[str, dict] = {
    "seed": dict(type=seed_value, help="seed of PPO and of the scenarios (default 0)"),
    "workers": dict(type=positive_int, help="processes stepping the teams, this one included (default 1)"),
    "device": dict(help="torch device: auto, cpu, cuda (default auto)"),
    "logdir": dict(help="folder for run folders (default runs/)"),
    "checkpoint_every": dict(type=positive_int, help="iterations between checkpoints (default 50)"),
    "progress_bar": dict(flag="--no-progress", action="store_const", const=False, help="no progress bar"),
    "evaluate": dict(action=argparse.BooleanOptionalAction, help="evaluate the final model on the recipe's protocol"),
}
#: Options of ``train`` that choose the recipe.
RECIPE_CHOICE = ("config", "recipe", "reward", "agents", "team_reward", "env", "scenes")


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``train`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "train",
        help="train a shared PPO policy through the curriculum",
        description="Train one PPO policy shared by every agent through the thesis's three curriculum stages. "
        "The recipe comes from --recipe (or --reward/--agents) or a settings file (--config: a recipe with run "
        "options, e.g. a run's config.yaml); the options given here change it. Defaults: the recipe's.",
    )
    parser.add_argument("--config", type=Path, help="settings file: a recipe with run: options (e.g. runs/X/config.yaml)")
    parser.add_argument("--recipe", help="a name listed by `sb3-formation recipes` or a recipe YAML file")
    parser.add_argument("--preset", dest="recipe", action=RenamedFlag, new="--recipe", help=argparse.SUPPRESS)
    parser.add_argument("--reward", choices=("angle", "bearing"), help="shape reward: angle (ch. 4/5) or bearing (ch. 5)")
    parser.add_argument("--agents", type=int, help="team size n >= 3 (every team)")
    parser.add_argument("--team-reward", action="store_true", default=None, help="every agent gets the team reward")
    parser.add_argument(
        "--env", type=assignment, action="append", metavar="FIELD=VALUE", help="set a FormationConfig field (repeatable)"
    )
    add_scenes_option(parser)
    for name, options in {**RECIPE_FLAGS, **RUN_FLAGS}.items():
        options = {key: value for key, value in options.items() if key != "flag"}
        parser.add_argument(flag_of(name), dest=name, default=None, **options)
    parser.add_argument("--resume", type=Path, metavar="RUN_DIR", help="continue a run from its latest checkpoint")
    add_trust_pickle_option(parser, "with --resume: load the checkpoint with SB3's load, unpickling what it holds")
    parser.add_argument(
        "--run-dir", type=Path, help="write the run into this new or empty folder (default: a new one under --logdir)"
    )
    parser.set_defaults(run=run)


def flag_of(name: str) -> str:
    """The command-line flag of an option of ``train`` (``progress_bar`` is ``--no-progress``)."""
    return {**RECIPE_FLAGS, **RUN_FLAGS}.get(name, {}).get("flag", "--" + name.replace("_", "-"))


def written_flag(name: str, value: object) -> str:
    """The flag of an option of ``train`` as the user wrote it (``--no-evaluate`` for ``evaluate`` set to False)."""
    negated = value is False and {**RECIPE_FLAGS, **RUN_FLAGS}.get(name, {}).get("action") is argparse.BooleanOptionalAction
    return "--no-" + flag_of(name).removeprefix("--") if negated else flag_of(name)


def settings_of(args: argparse.Namespace) -> TrainSettings:
    """The settings of ``sb3-formation train``: the recipe (or settings file), then the options given."""
    recipe = args.recipe
    if recipe is None and args.config is None and (args.reward is not None or args.team_reward):
        recipe = thesis_recipe_for(args.reward, args.agents, bool(args.team_reward))
    env = dict(args.env or [])
    if args.team_reward:
        env["team_reward"] = True
    if args.scenes is not None:
        env["scenes"] = args.scenes
    options = {name: getattr(args, name) for name in (*RECIPE_FLAGS, *RUN_FLAGS)}
    return layered_settings(args.config, recipe, env=env, agents=args.agents, **options)


def describe(settings: TrainSettings) -> str:
    """One line saying what a run trains: recipe, team sizes, budget, teams and policy."""
    recipe = settings.recipe
    shares = recipe.stage_time_shares()
    if shares is None:
        counts = ["until the time is up" if count is None else str(count) for count in recipe.stage_iterations()]
        stages = f"iterations per stage [{', '.join(counts)}]"
    else:
        stages = f"stages 1, 2 end at {shares[0]:.0%}, {shares[1]:.0%} of the time, stage 3 until the time is up"
    minutes = recipe.training_option("minutes")
    budget = "" if minutes is None else f", at most {minutes:g} min"
    policy = f"recurrent ({recipe.cell})" if recipe.recurrent else "MLP"
    sizes = "/".join(map(str, recipe.sizes))
    return f"training {recipe.name}: n={sizes}, {stages}{budget}, {recipe.n_envs} teams, {policy} policy"


def run(args: argparse.Namespace) -> int:
    """``sb3-formation train``: a new run, or ``--resume`` of an existing one."""
    if args.resume is not None:
        settings_given = (*RECIPE_CHOICE, "run_dir", *RECIPE_FLAGS, *(name for name in RUN_FLAGS if name != "progress_bar"))
        given = [name for name in settings_given if getattr(args, name) is not None]
        if given:
            flags = ", ".join(written_flag(name, getattr(args, name)) for name in given)
            raise ValueError(f"--resume continues a run with its own settings; drop {flags}")
        run_dir = resume(args.resume, trusted=args.trust_pickle, progress_bar=args.progress_bar)
        settings = load_settings(run_dir)
        if args.progress_bar is not None:
            settings = settings.replace_run(progress_bar=args.progress_bar)
    else:
        if args.trust_pickle:
            raise ValueError("--trust-pickle applies to --resume (a new run loads no model file)")
        settings = settings_of(args)
        print(describe(settings))
        run_dir = train(settings, command=args.command_line, run_dir=args.run_dir)
    print(f"run folder: {run_dir}")
    if settings.run.evaluate and (run_dir / FINAL_MODEL).exists():
        protocol = {**settings.recipe.evaluation, "workers": settings.run.workers}
        result = evaluate_target(run_dir, protocol, device=settings.run.device, progress_bar=settings.run.progress_bar)
        print_summary(result.summary)
    print(f"tensorboard --logdir {Path(run_dir).parent}")
    return 0
