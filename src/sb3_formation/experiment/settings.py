"""Run settings: the one place where the options of ``sb3-formation train`` (and the keys of its YAML files) are
declared, and the layering recipe -> YAML file -> flags as a function a notebook can call.

Each field of :class:`TrainSettings` carries its command-line flag in its metadata (see :func:`option`); the CLI builds
its parser from them, so a new setting is one new field.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from sb3_formation.env.config import FormationConfig
from sb3_formation.experiment.recipes import DEFAULT_RECIPE, Recipe, load_recipe, with_schedules
from sb3_formation.utils.checks import is_count, is_number
from sb3_formation.utils.deprecation import warn_renamed
from sb3_formation.utils.yaml_files import read_yaml

#: Keys of a run's ``evaluation:`` settings (arguments of :func:`~sb3_formation.experiment.evaluation.evaluate`).
EVALUATION_KEYS = frozenset({"episodes", "stage", "seed", "n_envs", "workers", "deterministic", "record"})
#: PPO settings a run may override (``ppo:`` in YAML), beyond those its recipe gives.
PPO_OVERRIDABLE = frozenset(
    {
        "n_steps",
        "batch_size",
        "n_epochs",
        "learning_rate",
        "gamma",
        "gae_lambda",
        "clip_range",
        "clip_range_vf",
        "target_kl",
        "ent_coef",
        "vf_coef",
        "max_grad_norm",
        "normalize_advantage",
        "policy_kwargs",
        "max_sequence_length",
    }
)
#: Largest seed: numpy's and PyTorch's generators take seeds in [0, 2**32 - 1].
MAX_SEED = 2**32 - 1


# Command-line value types ---------------------------------------------------------------------------------------------


def positive_int(text: str) -> int:
    """An integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def seed_value(text: str) -> int:
    """A seed: an integer in [0, 2**32 - 1]."""
    value = int(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be an integer in [0, 2**32 - 1], got {value}")
    return value


def positive_float(text: str) -> float:
    """A number > 0."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def stage_iterations(text: str) -> list[int]:
    """Three iteration counts ``A,B,C`` (curriculum stages 1, 2, 3)."""
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected three iteration counts A,B,C (stages 1, 2, 3), got {text!r}")
    return values


def assignment(text: str) -> tuple[str, object]:
    """``FIELD=VALUE``, the value read as YAML."""
    name, separator, value = text.partition("=")
    if not separator or not name:
        raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
    try:
        return name.strip(), read_yaml(value, f"the value of {name.strip()}")
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def option(help: str, **argparse_options: Any) -> dict[str, Any]:
    """Field metadata declaring a setting's command-line option: ``--<field-name>`` with these argparse options.

    :param help: the option's help text
    :param argparse_options: further ``add_argument`` options (``type``, ``choices``, ``action``, ``flag``, ...); a
        ``flag`` option replaces the default flag name
    """
    return {"cli": {"help": help, **argparse_options}}


def check_device(device: Any) -> None:
    """Refuse a torch device this machine does not have (``auto`` takes a GPU if there is one, else the CPU).

    :raises ValueError: not a device name, or a GPU that torch does not see here
    """
    try:
        kind = None if device == "auto" else torch.device(device).type
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:<index>, got {device!r}") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: torch sees no CUDA GPU on this machine; use --device auto or cpu")
    if kind not in (None, "cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:<index>, got {device!r}")


def check_seed(name: str, value: Any) -> None:
    """Refuse a seed that is not an integer in [0, :data:`MAX_SEED`].

    :param name: the setting, for the message
    """
    if not (is_count(value) and value <= MAX_SEED):
        raise ValueError(f"{name} must be an integer in [0, 2**32 - 1], got {value!r}")


@dataclass
class TrainSettings:
    """Everything a training run needs; the ``sb3-formation train`` options and the keys of its YAML file.

    Every setting left ``None`` takes its recipe's value (``recipe``: see :mod:`~sb3_formation.experiment.recipes`).

    :param recipe: recipe name (``sb3-formation recipes``) or the path of a recipe YAML file
    :param iterations: PPO iterations of curriculum stages 1, 2, 3
    :param n_envs: parallel teams
    :param workers: processes stepping the teams, this one included (the others are worker processes)
    :param seed: seed of PPO and of the teams' scenario generators
    :param device: torch device for PPO (``"auto"``, ``"cpu"``, ``"cuda"``)
    :param logdir: folder in which run folders are made
    :param checkpoint_every: write a checkpoint every this many iterations
    :param success_threshold: end curriculum stages 1-2 early at this rolling success rate
    :param progress_bar: show a progress bar
    :param seeds: the seeds of an experiment (``sb3-formation sweep`` trains one run per seed; ``train`` uses ``seed``)
    :param team_sizes: team sizes taken in turn (default: the recipe's ``team_sizes``; an ``n_agents`` in ``env``, e.g.
        ``--agents``, gives every team that size); a run's ``config.yaml`` records them resolved
    :param evaluation: evaluate the final model with these :func:`~sb3_formation.experiment.evaluation.evaluate`
        settings (``episodes``, ``stage``, ``seed``, ``n_envs``, ``workers``, ``deterministic``, ``record``) into ``eval/``
    :param recurrent: recurrent actor and critic
    :param cell: recurrent cell, ``"gru"`` or ``"lstm"``; only for recurrent policies
    :param steps: budget in agent-steps (rounded up to whole iterations), split between the stages in the
        proportions of the curriculum's iterations; schedules run over the budget
    :param minutes: budget in minutes of training wall-clock (not deterministic). Without ``steps`` and ``iterations``
        it replaces the recipe's budget: stages 1 and 2 end at their shares of the time in the curriculum's
        proportions (:meth:`stage_time_shares`) and stage 3 runs until the time is up; with them, training ends at
        whichever budget runs out first. Schedules run over whichever is further along (see
        :class:`~sb3_formation.sb3.callbacks.ClockedSchedule`)
    :param normalize_reward: divide rewards by a running std of the discounted return (SB3's ``VecNormalize``)
    :param eval_every: evaluate the deterministic policy on fixed-seed stage-3 episodes every this many iterations,
        log ``eval/*`` and keep ``best_model.zip``
    :param env: :class:`FormationConfig` fields overriding the recipe's (e.g. ``n_agents``)
    :param ppo: ``PPO`` keyword arguments overriding the recipe's (e.g. ``learning_rate``)
    """

    recipe: str = field(
        default=DEFAULT_RECIPE,
        metadata=option("recipe: a name listed by `sb3-formation recipes` or a recipe YAML file (overrides --reward)"),
    )
    iterations: tuple[int, int, int] | None = field(
        default=None,
        metadata=option("PPO iterations of stages 1,2,3 (default: the recipe's)", type=stage_iterations, metavar="A,B,C"),
    )
    n_envs: int | None = field(default=None, metadata=option("parallel teams (default: the recipe's)", type=positive_int))
    workers: int = field(
        default=1, metadata=option("processes stepping the teams, this one included (default 1)", type=positive_int)
    )
    seed: int = field(default=0, metadata=option("seed of PPO and of the scenarios (default 0)", type=seed_value))
    device: str = field(default="auto", metadata=option("torch device: auto, cpu, cuda (default auto)"))
    logdir: str = field(default="runs", metadata=option("folder for run folders (default runs/)"))
    checkpoint_every: int = field(
        default=50, metadata=option("iterations between checkpoints (default 50)", type=positive_int)
    )
    success_threshold: float | None = field(
        default=None, metadata=option("end stages 1-2 early at this rolling success rate", type=float)
    )
    progress_bar: bool = field(
        default=True, metadata=option("no progress bar", flag="--no-progress", action="store_const", const=False)
    )
    seeds: list[int] | None = None
    team_sizes: list[int] | None = None
    evaluation: dict[str, Any] | None = None
    recurrent: bool | None = field(
        default=None,
        metadata=option("recurrent actor and critic (default: the recipe's)", action=argparse.BooleanOptionalAction),
    )
    cell: str | None = field(default=None, metadata=option("recurrent cell (default: the recipe's)", choices=("gru", "lstm")))
    steps: int | None = field(
        default=None, metadata=option("budget in agent-steps (default: the recipe's, else its iterations)", type=positive_int)
    )
    minutes: float | None = field(
        default=None,
        metadata=option("budget in minutes of training wall-clock (replaces the recipe's budget)", type=positive_float),
    )
    normalize_reward: bool | None = field(
        default=None,
        metadata=option(
            "normalise rewards by a running return std (default: the recipe's)", action=argparse.BooleanOptionalAction
        ),
    )
    eval_every: int | None = field(
        default=None,
        metadata=option("evaluate every K iterations, keep best_model.zip (default: the recipe's)", type=positive_int),
    )
    env: dict[str, Any] = field(
        default_factory=dict,
        metadata=option(
            "override a FormationConfig field, e.g. --env max_steps=1000 (repeatable)",
            type=assignment,
            action="append",
            metavar="FIELD=VALUE",
        ),
    )
    ppo: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("env", "ppo"):
            if not isinstance(getattr(self, name), dict):
                raise ValueError(f"{name} must be a mapping of field names to values, got {getattr(self, name)!r}")
        if not isinstance(self.ppo.get("policy_kwargs", {}), dict):
            raise ValueError(f"ppo: policy_kwargs must be a mapping, got {self.ppo['policy_kwargs']!r}")
        check_device(self.device)
        check_seed("seed", self.seed)
        setup = self.recipe_record()  # validates the recipe
        self.config()  # validates the env overrides
        threshold = self.success_threshold
        if threshold is not None and not (is_number(threshold) and 0 <= threshold <= 1):
            raise ValueError(f"success_threshold must be a number in [0, 1] or null (the recipe's), got {threshold!r}")
        if self.minutes is not None and not (is_number(self.minutes) and self.minutes > 0):
            raise ValueError(f"minutes must be a finite number > 0, got {self.minutes!r}")
        if self.iterations is not None:
            iterations = self.iterations if isinstance(self.iterations, (list, tuple)) else ()
            # a run's config.yaml writes a stage 3 that runs until a time budget ends as null
            open_ended = self.minutes is not None and len(iterations) == 3 and iterations[2] is None
            counts = iterations[:2] if open_ended else iterations
            if not (len(iterations) == 3 and all(is_count(value) for value in counts)):
                raise ValueError(f"iterations must be three integers >= 0 (stages 1, 2, 3), got {self.iterations!r}")
            if not (open_ended or sum(counts) >= 1):
                raise ValueError(f"iterations must give at least one stage an iteration, got {self.iterations!r}")
            self.iterations = (*(int(value) for value in counts), *((None,) if open_ended else ()))
        optional = tuple(name for name in ("n_envs", "steps", "eval_every") if getattr(self, name) is not None)
        for name in ("workers", "checkpoint_every", *optional):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        unknown = sorted(set(self.ppo) - PPO_OVERRIDABLE - set(setup.ppo))
        if unknown:
            raise ValueError(f"unknown ppo setting(s) {unknown}; valid: {sorted(PPO_OVERRIDABLE | set(setup.ppo))}")
        if self.seeds is not None:
            self.seeds = list(self.seeds)
            if not self.seeds:
                raise ValueError(f"seeds must be a non-empty list of integers, got {self.seeds!r}")
            for seed in self.seeds:
                check_seed("each of seeds", seed)
        if self.team_sizes is not None:
            sizes = self.team_sizes
            if not (isinstance(sizes, (list, tuple)) and sizes and all(is_count(n) for n in sizes)):
                raise ValueError(f"team_sizes must be a non-empty list of team sizes, got {sizes!r}")
            self.team_sizes = list(sizes)
            for size in self.team_sizes:
                self.config().replace(n_agents=size)  # validates the size
        if self.workers > self.resolved_n_envs():
            raise ValueError(f"workers={self.workers} exceeds n_envs={self.resolved_n_envs()}: a worker steps whole teams")
        sizes, n_agents = self.resolved_team_sizes(), self.config().n_agents
        if "team_size" in self.ppo_kwargs()["policy_kwargs"] and set(sizes) != {n_agents}:
            raise ValueError(f"a team critic reads teams of n_agents={n_agents}; team_sizes lists {sizes}")
        if self.evaluation is not None:
            unknown = sorted(set(self.evaluation) - EVALUATION_KEYS) if isinstance(self.evaluation, dict) else None
            if unknown is None or unknown:
                raise ValueError(f"evaluation must map some of {sorted(EVALUATION_KEYS)} to values, got {self.evaluation!r}")
        if self.recurrent not in (None, True, False):
            raise ValueError(f"recurrent must be true, false or null (the recipe's), got {self.recurrent!r}")
        with_schedules(self.ppo_kwargs())  # validates recurrent, cell, the policy and the schedules
        if self.normalize_reward not in (None, True, False):
            raise ValueError(f"normalize_reward must be true, false or null (the recipe's), got {self.normalize_reward!r}")
        self.resolved_iterations()  # validates the budget against the curriculum
        if self.cell is not None and not self.resolved_recurrent():
            raise ValueError(f"cell {self.cell!r} applies to recurrent policies only; this run's policy is an MLP")
        if "max_sequence_length" in self.ppo and not self.resolved_recurrent():
            raise ValueError("ppo: max_sequence_length applies to recurrent policies only; this run's policy is an MLP")

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """Names of the settings (the valid top-level keys of a YAML file)."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainSettings:
        """Settings from a mapping (e.g. a YAML file); unknown keys are errors that list the valid ones."""
        values = with_current_keys(values)
        unknown = sorted(set(values) - set(cls.field_names()))
        if unknown:
            raise ValueError(f"unknown setting(s) {unknown}; valid: {list(cls.field_names())}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Every setting resolved (recipe values filled in, every env field and PPO setting) as plain YAML data."""
        values = dataclasses.asdict(self)
        values["iterations"] = list(self.resolved_iterations())
        values["n_envs"] = self.resolved_n_envs()
        values["success_threshold"] = self.resolved_success_threshold()
        values["recurrent"] = self.resolved_recurrent()
        for name in ("steps", "normalize_reward", "eval_every"):
            values[name] = self.resolved_training(name)
        values["cell"] = self.ppo_kwargs()["policy_kwargs"].get("cell") if values["recurrent"] else None
        values["env"] = _plain(dataclasses.asdict(self.config()))
        values["team_sizes"] = self.resolved_team_sizes()
        values["ppo"] = _plain({name: value for name, value in self.ppo_kwargs().items() if name != "policy"})
        values["ppo"]["policy_kwargs"].pop("cell", None)  # written once, as the top-level cell
        return values

    def recipe_record(self) -> Recipe:
        """The run's recipe."""
        return load_recipe(self.recipe)

    def config(self) -> FormationConfig:
        """The task configuration of this run."""
        return self.recipe_record().config(**self.env)

    def resolved_iterations(self) -> tuple[int, int, int | None]:
        """Iterations per stage: the recipe's unless given; with a steps budget, the budget's iterations (rounded up)
        split in the curriculum's proportions (:meth:`curriculum_proportions`; stage 3 gets what stages 1-2 leave);
        with only a time budget stage 3 is open-ended (``None``) and stages 1-2 end at shares of the time
        (:meth:`stage_time_shares`)."""
        iterations = self.iterations if self.iterations is not None else self.recipe_record().iterations
        budget = self.resolved_training("steps")
        if budget is None:
            if self.minutes is not None and self.iterations is None:
                return (iterations[0], iterations[1], None)
            return iterations
        total = -(-budget // self.steps_per_iteration())
        proportions = self.curriculum_proportions()
        first, second = (total * count // sum(proportions) for count in proportions[:2])
        return first, second, total - first - second

    def curriculum_proportions(self) -> tuple[int, int, int]:
        """The curriculum's iterations per stage as proportions, e.g. 5000 : 5000 : 15000 (thesis 5.3), which a steps
        budget and a time budget split in the same ratio (20, 20 and 60 %); an open-ended stage 3 counts as the
        recipe's."""
        first, second, third = self.iterations if self.iterations is not None else self.recipe_record().iterations
        return first, second, self.recipe_record().iterations[2] if third is None else third

    def stage_time_shares(self) -> tuple[float, float] | None:
        """With a time budget alone (stage 3 open-ended): the fractions of it after which stages 1 and 2 end, in the
        curriculum's proportions (:meth:`curriculum_proportions`: 0.2 and 0.4 for the thesis's); otherwise ``None``
        (stages end after their iterations)."""
        if self.resolved_iterations()[2] is not None:
            return None
        first, second, third = self.curriculum_proportions()
        total = first + second + third
        return first / total, (first + second) / total

    def budget_seconds(self) -> float | None:
        """The time budget in seconds, or ``None``."""
        return None if self.minutes is None else 60.0 * self.minutes

    def resolved_team_sizes(self) -> list[int]:
        """The team sizes taken in turn: as given, else the recipe's, else (or with an ``n_agents`` in ``env``) the
        task's ``n_agents``."""
        if self.team_sizes is not None:
            return list(self.team_sizes)
        sizes = self.recipe_record().team_sizes
        return [self.config().n_agents] if sizes is None or "n_agents" in self.env else list(sizes)

    def steps_per_iteration(self) -> int:
        """Agent-steps of one PPO iteration: n_steps in every slot (the agents of every team)."""
        sizes = self.resolved_team_sizes()  # team j has sizes[j % len(sizes)] agents
        return self.ppo_kwargs()["n_steps"] * sum(sizes[team % len(sizes)] for team in range(self.resolved_n_envs()))

    def resolved_training(self, name: str) -> Any:
        """A training feature (see :data:`~sb3_formation.experiment.recipes.TRAINING_DEFAULTS`): this run's, else the
        recipe's."""
        value = getattr(self, name, None)
        if value is not None:
            return value
        if name == "steps" and self.minutes is not None:
            return None  # a time budget replaces the recipe's step budget
        return self.recipe_record().training_option(name)

    def resolved_n_envs(self) -> int:
        """Number of teams, the recipe's unless given."""
        return self.n_envs if self.n_envs is not None else self.recipe_record().n_envs

    def resolved_success_threshold(self) -> float | None:
        """Success rate ending stages 1-2 early, the recipe's unless given."""
        return self.success_threshold if self.success_threshold is not None else self.recipe_record().success_threshold

    def resolved_recurrent(self) -> bool:
        """Whether the policy is recurrent: as given, else the recipe's choice."""
        return self.recurrent if self.recurrent is not None else self.recipe_record().recurrent

    def resolved_evaluation(self) -> dict[str, Any]:
        """The evaluation protocol: the recipe's, then this run's ``evaluation`` settings."""
        return {**self.recipe_record().evaluation, **(self.evaluation or {})}

    def ppo_kwargs(self) -> dict[str, Any]:
        """``PPO`` keyword arguments: the recipe's, then the overrides."""
        kwargs = self.recipe_record().ppo_kwargs(self.config(), self.recurrent, self.cell)
        overrides = dict(self.ppo)
        kwargs["policy_kwargs"] = {**kwargs["policy_kwargs"], **overrides.pop("policy_kwargs", {})}
        kwargs.update(overrides)
        return kwargs


def _plain(value: Any) -> Any:
    """Tuples to lists, recursively, so that YAML writes plain lists."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def with_current_keys(values: dict[str, Any]) -> dict[str, Any]:
    """A settings mapping with the key of earlier releases renamed, with a warning: ``preset`` -> ``recipe`` (run
    folders and YAML files written before recipes had their name)."""
    if "preset" not in values or "recipe" in values:
        return values
    warn_renamed("the settings key preset:", "recipe:", stacklevel=4)
    return {("recipe" if key == "preset" else key): value for key, value in values.items()}


def reduce_to_overrides(values: dict[str, Any]) -> dict[str, Any]:
    """A settings mapping whose ``env:`` and ``ppo:`` keep only what differs from its own recipe's values.

    A run's ``config.yaml`` holds every resolved value; reduced, it can be reused with another recipe or team size
    (``--config old/config.yaml --reward bearing``) without pinning the old recipe's coefficients.
    """
    values = with_current_keys(values)
    ppo = values.get("ppo") or {}
    if not (
        isinstance(values.get("env") or {}, dict)
        and isinstance(ppo, dict)
        and isinstance(ppo.get("policy_kwargs") or {}, dict)
    ):
        return values  # reported by TrainSettings
    try:
        setup = load_recipe(values.get("recipe", DEFAULT_RECIPE))
        defaults = _plain(dataclasses.asdict(setup.config()))
        env = {name: value for name, value in (values.get("env") or {}).items() if defaults.get(name) != _plain(value)}
        config = setup.config(**env)
        kwargs = setup.ppo_kwargs(config, values.get("recurrent"), values.get("cell"))
    except (TypeError, ValueError):
        return values  # reported by TrainSettings
    given = _plain({name: value for name, value in kwargs.items() if name != "policy"})
    ppo = dict(values.get("ppo") or {})
    policy_kwargs = {
        name: value
        for name, value in (ppo.pop("policy_kwargs", None) or {}).items()
        if given["policy_kwargs"].get(name) != _plain(value)
    }
    ppo = {name: value for name, value in ppo.items() if name not in given or given[name] != _plain(value)}
    if policy_kwargs:
        ppo["policy_kwargs"] = policy_kwargs
    return {**values, "env": env, "ppo": ppo}


def read_settings_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The settings mapping of a YAML file (a run's ``config.yaml`` or an experiment), reduced to overrides.

    :raises FileNotFoundError: no such file
    :raises ValueError: not YAML, or not a mapping
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such settings file {path}")
    values = read_yaml(path.read_text(), str(path)) or {}
    if not isinstance(values, dict):
        raise ValueError(f"{path} must hold a mapping of settings, not {type(values).__name__}")
    return reduce_to_overrides(values)


def layered_settings(config_file: str | os.PathLike[str] | None = None, **flags: Any) -> TrainSettings:
    """Settings layered as ``sb3-formation train`` layers them: the recipe, then a YAML file, then ``flags``.

    :param config_file: a YAML file of settings (a run's ``config.yaml`` or an experiment), or ``None``
    :param flags: settings that override the file (``None`` values are ignored); ``env`` is merged field by field into
        the file's ``env:``
    """
    values = read_settings_file(config_file) if config_file is not None else {}
    flags = {name: value for name, value in flags.items() if value is not None}
    if not isinstance(values.get("env") or {}, dict):
        raise ValueError(f"{config_file}: env must be a mapping of field names to values, got {values['env']!r}")
    env = {**(values.get("env") or {}), **flags.pop("env", {})}
    return TrainSettings.from_dict({**values, **flags, "env": env})


def load_settings(run_dir: str | os.PathLike[str]) -> TrainSettings:
    """The settings a run folder was made with (its ``config.yaml``)."""
    path = Path(run_dir) / "config.yaml"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run folder: {path} is missing")
    values = read_yaml(path.read_text(), str(path))
    if not isinstance(values, dict):
        raise ValueError(f"{path} must hold a mapping of settings, not {type(values).__name__}")
    try:
        return TrainSettings.from_dict(values)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path} holds invalid settings: {error}") from None


def cli_options() -> list[tuple[str, dict[str, Any]]]:
    """(field name, argparse options with ``flag``) of every setting that has a command-line option, in field order."""
    options = []
    for item in dataclasses.fields(TrainSettings):
        if "cli" in item.metadata:
            arguments = dict(item.metadata["cli"])
            arguments.setdefault("flag", "--" + item.name.replace("_", "-"))
            options.append((item.name, arguments))
    return options


#: Convert an option's parsed value to the setting's value (``--env`` gives a list of (field, value) pairs).
CLI_CONVERSIONS: dict[str, Callable[[Any], Any]] = {"env": dict}
