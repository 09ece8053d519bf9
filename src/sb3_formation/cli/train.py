"""``sb3-formation train``: train a shared PPO policy through the curriculum, or resume a run.

The options that change a recipe or a run are made from the fields declared with
:func:`~sb3_formation.experiment.sections.option` (:func:`~sb3_formation.experiment.recipes.recipe_options`): the flag,
its value's type and its help come from the field, so each is declared once.
"""

from __future__ import annotations

import argparse
import re
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from sb3_formation.cli.common import add_recipe_option, add_scenes_option, add_trust_pickle_option, assignment, print_summary
from sb3_formation.experiment.evaluation import evaluate_target
from sb3_formation.experiment.recipes import (
    RecipeOption,
    TrainSettings,
    layered_settings,
    load_settings,
    recipe_options,
    thesis_recipe_for,
)
from sb3_formation.experiment.runs import FINAL_MODEL
from sb3_formation.experiment.training import resume, train
from sb3_formation.utils.arguments import output_path

#: Options of ``train`` that choose the recipe or change its task, beside the recipe's fields.
RECIPE_CHOICE = ("recipe", "reward", "agents", "team_reward", "scenes")


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Add the ``train`` subcommand to ``commands``."""
    parser = commands.add_parser(
        "train",
        help="train a shared PPO policy through the curriculum",
        description="Train one PPO policy shared by every agent through the thesis's three curriculum stages. "
        "The recipe comes from --recipe (or --reward/--agents): a run's config.yaml trains that run's recipe again, "
        "with its run options. The options given here change it. Defaults: the recipe's.",
    )
    add_recipe_option(parser, "a name listed by `sb3-formation recipes`, or a recipe YAML file (e.g. runs/X/config.yaml)")
    parser.add_argument("--reward", choices=("angle", "bearing"), help="shape reward: angle (ch. 4/5) or bearing (ch. 5)")
    parser.add_argument("--agents", type=int, help="team size n >= 3 (every team)")
    parser.add_argument("--team-reward", action="store_true", default=None, help="every agent gets the team reward")
    add_scenes_option(parser)
    for option in recipe_options():
        parser.add_argument(option.flag, dest=option.name, default=None, help=help_text(option.help), **value_kind(option))
    parser.add_argument("--resume", type=output_path, metavar="RUN_DIR", help="continue a run from its latest checkpoint")
    add_trust_pickle_option(parser, "with --resume: load the checkpoint with SB3's load, unpickling what it holds")
    parser.add_argument(
        "--run-dir", type=output_path, help="write the run into this new or empty folder (default: a new one under --logdir)"
    )
    parser.set_defaults(run=run)


def help_text(doc: str) -> str:
    """A field's ``:param:`` text as a flag's help: Sphinx roles and literals as plain words, ``%`` escaped for
    argparse."""
    text = re.sub(r":\w+:`~?([^`]+)`", lambda match: match[1].rsplit(".", 1)[-1], doc)
    return re.sub(r"``([^`]+)``", r"\1", text).replace("%", "%%")


class Assignments(argparse.Action):
    """``FIELD=VALUE`` (repeatable, :func:`~sb3_formation.cli.common.assignment`): the mapping of the fields given."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any, flag: Any = None) -> None:
        name, value = values
        setattr(namespace, self.dest, {**(getattr(namespace, self.dest) or {}), name: value})


def integers(count: int | None) -> Callable[[str], tuple[int, ...]]:
    """The type of a flag of comma-separated integers (``count`` of them, or any number of at least one)."""

    def parse(text: str) -> tuple[int, ...]:
        try:
            values = tuple(int(part) for part in text.split(","))
        except ValueError:
            values = ()
        if not values or (count is not None and len(values) != count):
            raise argparse.ArgumentTypeError(f"expected {count or 'some'} comma-separated integers, got {text!r}")
        return values

    return parse


def value_kind(option: RecipeOption) -> dict[str, Any]:
    """argparse's ``action``, ``type``, ``choices`` and ``metavar`` for an option, from its field's type: a switch
    (``--x``/``--no-x``) for a bool, comma-separated integers for a tuple of them, repeatable ``FIELD=VALUE`` for a
    mapping, else the type itself."""
    hint = option.hint
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        hint = next(kind for kind in typing.get_args(hint) if kind is not type(None))  # an unset field: no flag given
    if option.choices is not None:
        return {"choices": option.choices}
    if hint is bool:
        return {"action": argparse.BooleanOptionalAction}
    if typing.get_origin(hint) is tuple:
        count = None if Ellipsis in typing.get_args(hint) else len(typing.get_args(hint))
        return {"type": integers(count), "metavar": ",".join(["N"] * (count or 2)) + ("" if count else ",...")}
    if typing.get_origin(hint) in (dict, Mapping):
        return {"type": assignment, "action": Assignments, "metavar": "FIELD=VALUE"}
    return {"type": hint}


def written_flag(option: RecipeOption, value: object) -> str:
    """An option's flag as the user wrote it (``--no-evaluate`` for a switch set to false)."""
    return "--no-" + option.flag.removeprefix("--") if value is False else option.flag


def settings_of(args: argparse.Namespace) -> TrainSettings:
    """The settings of ``sb3-formation train``: the recipe with its run options, then the options given."""
    recipe = args.recipe
    if recipe is None and (args.reward is not None or args.team_reward):
        recipe = thesis_recipe_for(args.reward, args.agents, bool(args.team_reward))
    options = {option.name: getattr(args, option.name) for option in recipe_options()}
    task = {"team_reward": True if args.team_reward else None, "scenes": args.scenes}
    options["env"] = {**(options["env"] or {}), **{name: value for name, value in task.items() if value is not None}}
    return layered_settings(recipe, agents=args.agents, **options)


def describe(settings: TrainSettings) -> str:
    """One line saying what a run trains: recipe, team sizes, budget, teams and policy."""
    recipe = settings.recipe
    shares = recipe.stage_time_shares()
    if shares is None:
        counts = ["until the time is up" if count is None else str(count) for count in recipe.stage_iterations()]
        stages = f"iterations per stage [{', '.join(counts)}]"
    else:
        stages = f"stages 1, 2 end at {shares[0]:.0%}, {shares[1]:.0%} of the time, stage 3 until the time is up"
    minutes = recipe.training.minutes
    budget = "" if minutes is None else f", at most {minutes:g} min"
    policy = f"recurrent ({recipe.cell})" if recipe.recurrent else "MLP"
    sizes = "/".join(map(str, recipe.sizes))
    return f"training {recipe.name}: n={sizes}, {stages}{budget}, {recipe.n_envs} teams, {policy} policy"


def check_resume_options(args: argparse.Namespace) -> None:
    """Refuse the options that would change a resumed run: it continues with its own recipe and run options (only
    whether to show a progress bar may change).

    :raises ValueError: naming the options to drop, as written
    """
    options = [option for option in recipe_options() if option.field != "progress_bar"]
    given = [f"--{name.replace('_', '-')}" for name in (*RECIPE_CHOICE, "run_dir") if getattr(args, name) is not None]
    given += [written_flag(option, getattr(args, option.name)) for option in options if getattr(args, option.name) is not None]
    if given:
        raise ValueError(f"--resume continues a run with its own settings; drop {', '.join(given)}")


def run(args: argparse.Namespace) -> int:
    """``sb3-formation train``: a new run, or ``--resume`` of an existing one."""
    if args.resume is not None:
        check_resume_options(args)
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
        result = evaluate_target(
            run_dir,
            settings.recipe.evaluation,
            workers=settings.run.workers,
            device=settings.run.device,
            progress_bar=settings.run.progress_bar,
        )
        print_summary(result.summary)
    print(f"tensorboard --logdir {Path(run_dir).parent}")
    return 0
