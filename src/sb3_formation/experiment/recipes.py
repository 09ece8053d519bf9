"""Recipes: a whole training recipe as one record of data, in one YAML format, read, merged and written here.

A recipe names the task, the policy, the PPO settings, the curriculum, the number of parallel teams, the evaluation
protocol and optional training features (a budget, a residual controller, imitation, the safety filter), each a typed
section (:mod:`~sb3_formation.experiment.sections`). The same format serves the recipes shipped in this package
(``sb3_formation/experiment/shipped_recipes/``, each line citing its table, equation or section), the recipes of the
thesis's runs and of the shipped policies in the repository's ``recipes/`` folder, a user's file and a run's own
``config.yaml``: the complete recipe the run trained (:meth:`Recipe.to_dict`). A recipe file may carry a ``run:``
section, the options of a run that are not the recipe (:class:`~sb3_formation.experiment.sections.RunOptions`: seed,
device, workers, folders, checkpoints, progress), so ``sb3-formation train --recipe runs/X/config.yaml --seed 1`` trains
a run's recipe again.

A recipe file may name a ``base:`` recipe (a shipped name, or a path relative to the file) and give only what differs:
its sections merge into the base's key by key (:func:`merge_recipe`), as RL Zoo's YAML anchors do. :func:`load_recipe`
resolves the chain once into a frozen :class:`Recipe`, :func:`load_settings` reads the file's ``run:`` section too, and
:func:`layered_settings` puts the options of ``sb3-formation train`` (:func:`recipe_options`) over both.
"""

from __future__ import annotations

import inspect
import os
import typing
from dataclasses import MISSING, dataclass, field, fields
from functools import cache
from pathlib import Path
from typing import Any

import yaml
from stable_baselines3 import PPO

from sb3_formation.controllers import controller_from_spec
from sb3_formation.controllers.base import Controller, TeamPolicy
from sb3_formation.controllers.residual import ResidualPolicy, check_residual_scale
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.observations import observation_fields
from sb3_formation.experiment.sections import (
    OPTION,
    SECTIONS,
    CurriculumSection,
    DisturbancesSection,
    EnvSection,
    EvaluationSection,
    ImitationSection,
    PolicySection,
    PPOSection,
    ResidualSection,
    RunOptions,
    SafetySection,
    TrainingSection,
    field_docs,
    keys_error,
    option,
    plain,
    schedule,
)
from sb3_formation.safety.filter import SafetyGains
from sb3_formation.safety.qp import check_solver
from sb3_formation.sb3.imitation import ImitationSettings
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy
from sb3_formation.sb3.vec_env import uses_team_critic
from sb3_formation.utils.checks import check_name, is_count, is_integer
from sb3_formation.utils.files import atomic_write
from sb3_formation.utils.yaml_files import read_yaml_file

#: The folder of the shipped recipes, one ``<name>.yaml`` each.
RECIPES_FOLDER = Path(__file__).with_name("shipped_recipes")
#: The recipe used when none is named.
DEFAULT_RECIPE = "ch5-bearing"
#: The key of a recipe file that holds the run options, not the recipe.
RUN_KEY = RunOptions.key
#: The sections a recipe may leave out, written ``{}`` when off: null or ``{}`` in a derived file switches one off.
OPTIONAL_SECTIONS = ("residual", "imitation", "safety", "disturbances")
#: The most teams a recipe may play at once (``n_envs``): 70 times the thesis's 14 (thesis 5.3).
MAX_TEAMS = 1024
#: The most bytes a PPO iteration's rollout may hold (SB3's buffer of float32 observations and the values below, for
#: every agent-step): a quarter of a 16 GiB machine.
MAX_ROLLOUT_BYTES = 4 << 30
#: Values SB3's rollout buffer keeps per agent-step beside the observation: the action (2), reward, return, episode
#: start, value, log-probability and advantage.
ROLLOUT_VALUES = 8
#: SB3's ``n_steps`` when a recipe gives none.
PPO_DEFAULT_N_STEPS: int = inspect.signature(PPO.__init__).parameters["n_steps"].default
#: The recurrent cell when a recurrent recipe names none (:class:`RecurrentFormationPolicy`'s default).
DEFAULT_CELL: str = inspect.signature(RecurrentFormationPolicy.__init__).parameters["cell"].default
#: The longest ``base:`` chain a recipe file may have (the shipped recipes are at most 3 deep).
MAX_BASE_CHAIN = 32


@dataclass(frozen=True)
class Recipe:
    """One training recipe (see the module docstring), resolved: its ``base:`` merged in, each section typed.

    :param name: the recipe's name (its ``name:`` key, else its file's stem); it begins its runs' folder names
    :param description: one line for ``sb3-formation recipes``
    :param env: the task
    :param policy: the network and the policy class's keyword arguments
    :param ppo: SB3's PPO keyword arguments
    :param curriculum: the stages' iterations and success gate
    :param evaluation: the protocol that measures the trained policy
    :param n_envs: parallel teams during training (each team is one env of the VecEnv, its agents the env's slots)
    :param training: training features and the budget (default: the thesis's, none of them)
    :param residual: train a bounded correction of a controller (default: none)
    :param imitation: pretrain the actor on a controller's actions (default: none)
    :param safety: train behind the safety filter (default: none)
    :param disturbances: train under randomised disturbances (default: the ideal world)
    :param team_sizes: teams of several sizes in one rollout, taken in turn (team j has team_sizes[j % len(team_sizes)]
        agents; unset: every team has the task's n_agents); a policy trained on several sizes acts in teams of any size
    :param source: the file it was read from
    """

    name: str
    description: str
    env: EnvSection
    policy: PolicySection
    ppo: PPOSection
    curriculum: CurriculumSection
    evaluation: EvaluationSection
    n_envs: int = option()  # required: option() gives no default
    training: TrainingSection = field(default_factory=TrainingSection)
    residual: ResidualSection | None = None
    imitation: ImitationSection | None = None
    safety: SafetySection | None = None
    disturbances: DisturbancesSection | None = None
    team_sizes: tuple[int, ...] | None = option(None)
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        try:
            self._check_fields()
            self._check_policy()
            self._check_teams()
            self._check_controllers()
            self._check_rollout_size()
        except ValueError as error:
            raise ValueError(f"recipe {self.name!r}: {error}") from error

    def _check_fields(self) -> None:
        """The name, the sections' types and the number of teams."""
        if not (isinstance(self.name, str) and self.name):
            raise ValueError("its name must be a non-empty string")
        check_name(self.name, "recipe name")  # it begins the name of a run's folder under --logdir
        for key, section in SECTIONS.items():
            value = getattr(self, key)
            if not (isinstance(value, section) or (value is None and key in OPTIONAL_SECTIONS)):
                raise ValueError(f"{key} must be a {section.__name__} (Recipe.from_dict reads mappings), got {value!r}")
        if not (is_integer(self.n_envs) and self.n_envs >= 1):
            raise ValueError(f"n_envs must be an integer >= 1, got {self.n_envs!r}")
        if self.n_envs > MAX_TEAMS:
            raise ValueError(f"n_envs must be at most {MAX_TEAMS} (teams played at once), got {self.n_envs}")

    def _check_policy(self) -> None:
        """What the policy's choices allow: no recurrent team critic, a sequence length for recurrent policies only."""
        if self.recurrent and self.team_critic:
            raise ValueError(
                "the task's team reward chooses the team critic, which has no recurrent version: set policy: "
                "recurrent: false or team_critic: false"
            )
        if self.ppo.max_sequence_length is not None and not self.recurrent:
            raise ValueError("ppo: max_sequence_length applies to recurrent policies only")

    def _check_teams(self) -> None:
        """Every team size is a valid task, and a team critic reads teams of the task's size."""
        sizes = self.team_sizes
        if sizes is not None:
            if not (isinstance(sizes, (list, tuple)) and sizes and all(is_count(size) for size in sizes)):
                raise ValueError(f"team_sizes must be a non-empty list of team sizes, got {sizes!r}")
            for size in sizes:
                try:
                    self.config(n_agents=size)
                except ValueError as error:
                    raise ValueError(f"team_sizes: {error}") from error
            object.__setattr__(self, "team_sizes", tuple(int(size) for size in sizes))
        n_agents = self.config().n_agents
        if self.team_critic and set(self.sizes) != {n_agents}:
            raise ValueError(f"a team critic reads teams of n_agents={n_agents}; team_sizes lists {self.sizes}")

    def _check_controllers(self) -> None:
        """The controllers of the residual and imitation sections act in the task."""
        if self.residual is not None:
            try:
                residual_base(self.residual.to_dict(), self.config())
            except (TypeError, ValueError) as error:
                raise ValueError(f"residual: {error}") from error
        if self.imitation is not None:
            if self.recurrent or self.residual is not None:
                raise ValueError("imitation pretrains an MLP actor of whole actions: not recurrent, not residual")
            try:
                self.teacher(self.config())
            except (TypeError, ValueError) as error:
                raise ValueError(f"imitation: {error}") from error

    def _check_rollout_size(self) -> None:
        """A PPO iteration's rollout fits in :data:`MAX_ROLLOUT_BYTES`."""
        features = max(sum(item.size for item in observation_fields(self.config(n_agents=n))) for n in self.sizes)
        rollout = self.steps_per_iteration() * (features + ROLLOUT_VALUES) * 4  # float32
        if rollout > MAX_ROLLOUT_BYTES:
            raise ValueError(
                f"a PPO iteration of n_steps={self.n_steps} in {self.n_envs} teams would hold {rollout / 2**30:.1f} GiB "
                f"of rollout, beyond the limit of {MAX_ROLLOUT_BYTES / 2**30:g} GiB: lower ppo: n_steps or n_envs"
            )

    # Reading and writing ----------------------------------------------------------------------------------------------

    @classmethod
    def from_dict(cls, values: Any, source: Path | None = None) -> Recipe:
        """A recipe from its YAML mapping (its ``base:`` already merged in, see :func:`load_recipe`); unknown or missing
        keys are errors that name the valid ones. A ``run:`` section (:class:`RunOptions`) is not part of the recipe.

        :param values: the mapping
        :param source: the file it was read from
        """
        if not isinstance(values, dict):
            raise ValueError(f"a recipe must be a mapping, not {type(values).__name__}")
        values = {key: value for key, value in values.items() if key != RUN_KEY}
        where = f"recipe {values.get('name')!r}"
        keys = [item.name for item in fields(cls) if item.name != "source"]
        required = [item.name for item in fields(cls) if item.default is MISSING and item.default_factory is MISSING]
        unknown, missing = sorted(set(values) - set(keys), key=str), [key for key in required if key not in values]
        if unknown or missing:
            raise keys_error(where, required, [key for key in keys if key not in required], unknown, missing)
        try:
            sections = {key: _read_section(key, values[key]) for key in SECTIONS if key in values}
        except ValueError as error:
            raise ValueError(f"{where}: {error}") from error
        return cls(**{**values, **sections}, source=source)

    def to_dict(self) -> dict[str, Any]:
        """The complete recipe as plain YAML data: every env field, every training feature, the policy's choices and
        the team sizes resolved. Read back (:meth:`from_dict`) it writes the same mapping again and does not depend on the
        shipped recipes or the task defaults it was made from; a run writes it as its ``config.yaml``."""
        values = self._as_given()
        policy = {"recurrent": self.recurrent, **self.policy.kwargs(), "team_critic": self.team_critic}
        if self.recurrent:
            policy["cell"] = self.cell
        env = {"task": self.env.task, **self.config().to_dict()}
        return plain({**values, "env": env, "policy": policy, "team_sizes": self.sizes})

    def _as_given(self) -> dict[str, Any]:
        """The recipe's mapping as its sections hold it (the task's overrides, not every field; the policy's choices as
        given): what :meth:`with_changes` merges into."""
        sections = {key: {} if getattr(self, key) is None else getattr(self, key).to_dict() for key in SECTIONS}
        return {
            "name": self.name,
            "description": self.description,
            **{key: sections[key] for key in ("env", "policy", "ppo", "curriculum")},
            "n_envs": self.n_envs,
            "team_sizes": None if self.team_sizes is None else list(self.team_sizes),
            **{key: sections[key] for key in ("evaluation", "training", *OPTIONAL_SECTIONS)},
        }

    def with_changes(self, changes: dict[str, Any]) -> Recipe:
        """This recipe with ``changes`` (a partial recipe mapping) merged in as a ``base:`` merges a file
        (:func:`merge_recipe`), e.g. ``{"n_envs": 2, "env": {"max_steps": 60}}``; the result is validated."""
        if not changes:
            return self
        return Recipe.from_dict(merge_recipe(self._as_given(), changes), source=self.source)

    # What the recipe means --------------------------------------------------------------------------------------------

    @property
    def recurrent(self) -> bool:
        """Whether the recipe's policy is recurrent."""
        return self.policy.recurrent

    @property
    def cell(self) -> str | None:
        """The recurrent cell (``None`` for an MLP)."""
        return (self.policy.cell or DEFAULT_CELL) if self.recurrent else None

    @property
    def team_critic(self) -> bool:
        """Whether the critic reads the whole team (fig. 4.3): as the recipe says, else exactly with the team reward
        (:func:`~sb3_formation.sb3.vec_env.uses_team_critic`, the rule of the env's team observations too)."""
        return uses_team_critic(self.config(), self.policy.team_critic)

    @property
    def sizes(self) -> list[int]:
        """The team sizes taken in turn: ``team_sizes``, else the task's ``n_agents``."""
        return list(self.team_sizes) if self.team_sizes is not None else [self.config().n_agents]

    @property
    def iterations(self) -> tuple[int, int, int]:
        """The curriculum's iterations of stages 1, 2 and 3 (with a budget, their proportions)."""
        return self.curriculum.iterations

    @property
    def success_threshold(self) -> float | None:
        """Rolling success rate that ends stages 1-2 early, or ``None``."""
        return self.curriculum.success_threshold

    @property
    def n_steps(self) -> int:
        """Steps each slot plays per PPO iteration."""
        return PPO_DEFAULT_N_STEPS if self.ppo.n_steps is None else self.ppo.n_steps

    def config(self, **changes: Any) -> FormationConfig:
        """The recipe's task configuration, with ``changes`` (:class:`FormationConfig` fields) applied."""
        return self.env.config(**changes)

    def training_config(self, **changes: Any) -> FormationConfig:
        """The task its training episodes are played in: :meth:`config` under the ``disturbances`` section's randomised
        disturbances, if any."""
        world = {} if self.disturbances is None else {"disturbances": self.disturbances.disturbances()}
        return self.config(**{**world, **changes})

    def ppo_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``PPO`` (or, for a recurrent policy, :class:`RecurrentFormationPPO`), with the policy
        class and its keyword arguments (schedules as data: :func:`with_schedules` turns them into SB3's); a team critic
        reads the task's team size."""
        policy_kwargs = self.policy.kwargs()
        if self.recurrent:
            return {
                "policy": RecurrentFormationPolicy,
                **self.ppo.to_dict(),
                "policy_kwargs": {**policy_kwargs, "cell": self.cell},
            }
        if self.team_critic:
            policy_kwargs["team_size"] = self.config().n_agents
        return {"policy": FormationPolicy, **self.ppo.to_dict(), "policy_kwargs": policy_kwargs}

    def steps_per_iteration(self) -> int:
        """Agent-steps of one PPO iteration: n_steps in every slot (the agents of every team)."""
        sizes = self.sizes  # team j has sizes[j % len(sizes)] agents
        return self.n_steps * sum(sizes[team % len(sizes)] for team in range(self.n_envs))

    def stage_iterations(self) -> tuple[int, int, int | None]:
        """PPO iterations of stages 1, 2 and 3 as trained. Without a budget, the curriculum's iterations. With a
        ``steps`` budget, its iterations (rounded up) split in the curriculum's proportions (stage 3 gets what stages
        1-2 leave); a ``minutes`` budget beside it ends training early if it runs out first. With a ``minutes`` budget
        alone, stage 3 is open-ended (``None``): stages 1-2 end at their shares of the time
        (:meth:`stage_time_shares`), stage 3 when the time is up."""
        budget = self.training.steps
        if budget is None:
            if self.training.minutes is not None:
                return (*self.iterations[:2], None)
            return self.iterations
        total = -(-budget // self.steps_per_iteration())
        first, second = (total * count // sum(self.iterations) for count in self.iterations[:2])
        return first, second, total - first - second

    def stage_time_shares(self) -> tuple[float, float] | None:
        """With a time budget alone: the fractions of it after which stages 1 and 2 end, in the curriculum's
        proportions (0.2 and 0.4 for the thesis's 5000 : 5000 : 15000); otherwise ``None`` (stages end after their
        iterations)."""
        if self.stage_iterations()[2] is not None:
            return None
        first, second, third = self.iterations
        return first / (first + second + third), (first + second) / (first + second + third)

    def budget_seconds(self) -> float | None:
        """The time budget in seconds, or ``None``."""
        minutes = self.training.minutes
        return None if minutes is None else 60.0 * minutes

    @property
    def safety_penalty(self) -> float:
        """The reward penalty per unit of the filter's change of an action (0 without a safety section)."""
        return 0.0 if self.safety is None else self.safety.penalty

    def imitation_settings(self) -> ImitationSettings | None:
        """How the actor is pretrained before PPO (``None`` without an imitation section)."""
        return None if self.imitation is None else self.imitation.imitation_settings()

    def teacher(self, config: FormationConfig) -> Controller | None:
        """The controller the actor imitates before PPO (``None`` without an imitation section).

        :param config: the task the controller acts in
        """
        return None if self.imitation is None else controller_from_spec(self.imitation.to_dict(), config)


def _read_section(key: str, values: Any) -> Any:
    """The section ``key`` of a recipe mapping: ``None`` for an optional section that is null or ``{}``, the defaults
    for a null ``training``."""
    if key in OPTIONAL_SECTIONS and not values:
        return None
    return SECTIONS[key].from_dict({} if key == "training" and values is None else values)


def read_safety_gains(section: SafetySection | dict[str, Any] | None) -> SafetyGains | None:
    """The safety filter's gains of a recipe's ``safety`` section (the section, or its mapping as a run's model file
    records it), or ``None`` for no section (no filter): the one reading of the gains, which training a shielded
    policy (:meth:`Recipe.safety_gains`) and loading it (:func:`~sb3_formation.experiment.runs.load_trained`) share.

    :raises ValueError: an unknown or invalid gain, or a solver not installed here
    """
    read: SafetySection | None = _read_section(SafetySection.key, section) if isinstance(section, dict) else section
    if read is None:
        return None
    gains = SafetyGains.from_dict(read.gains)
    check_solver(gains.solver)  # (a section read from a model file was checked on another machine)
    return gains


@dataclass(frozen=True)
class TrainSettings:
    """Everything a training run needs: what is trained (``recipe``) and how the run is carried out (``run``, the
    recipe file's ``run:`` section).

    :param recipe: the resolved recipe
    :param run: the run options
    """

    recipe: Recipe
    run: RunOptions = field(default_factory=RunOptions)

    def __post_init__(self) -> None:
        if self.run.workers > self.recipe.n_envs:
            raise ValueError(f"workers={self.run.workers} exceeds n_envs={self.recipe.n_envs}: a worker steps whole teams")

    @classmethod
    def from_dict(cls, values: Any, source: Path | None = None) -> TrainSettings:
        """Settings from a recipe mapping with an optional ``run:`` section (its ``base:`` already merged in)."""
        recipe = Recipe.from_dict(values, source)
        return cls(recipe, RunOptions.from_dict(values.get(RUN_KEY) or {}))

    def replace_run(self, **options: Any) -> TrainSettings:
        """The same recipe with other run options (fields of :class:`RunOptions`)."""
        return TrainSettings(self.recipe, self.run.replace(**options))

    def to_dict(self) -> dict[str, Any]:
        """The complete recipe (:meth:`Recipe.to_dict`) with the run options under ``run:``: a run's ``config.yaml``."""
        return {**self.recipe.to_dict(), RUN_KEY: self.run.to_dict()}


# Files --------------------------------------------------------------------------------------------------------------


def merge_recipe(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``changes`` over ``base``, as a ``base:`` key merges a recipe file: the sections (:data:`SECTIONS`) merge key by
    key; every other value, and every value inside a section, replaces the base's (lists and ``net_arch`` whole).

    :param base: the base recipe's mapping
    :param changes: the overriding mapping
    """
    merged = dict(base)
    for key, value in changes.items():
        if key in SECTIONS and isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged


def recipe_names() -> list[str]:
    """Names of the recipes shipped with the package."""
    return sorted(path.stem for path in RECIPES_FOLDER.glob("*.yaml"))


def recipe_path(name: str | os.PathLike[str], relative_to: Path | None = None) -> Path:
    """The file of a recipe: a shipped name, or the path of a YAML file (relative paths from ``relative_to``).

    :raises ValueError: an unknown name (the valid ones are listed) or no such file
    """
    if not isinstance(name, (str, os.PathLike)):
        raise ValueError(f"recipe must be a recipe name or the path of a recipe YAML file, got {name!r}")
    path = Path(name)
    if path.suffix not in (".yaml", ".yml"):
        if str(name) not in recipe_names():
            raise ValueError(f"unknown recipe {str(name)!r}; recipes: {', '.join(recipe_names())}, or a recipe YAML file")
        return RECIPES_FOLDER / f"{name}.yaml"
    path = path if relative_to is None or path.is_absolute() else relative_to / path
    if not path.is_file():
        raise ValueError(f"no recipe file {path}")
    return path


def read_recipe_file(path: Path, chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A recipe file's mapping with its ``base:`` chain merged in (:func:`merge_recipe`), ``name`` and ``run``
    included.

    :param path: the file
    :param chain: the files that named this one as their base (to refuse a cycle)
    :raises ValueError: not YAML, not a mapping, or a ``base:`` that is unknown, names a file of its own chain, or
        makes a chain longer than :data:`MAX_BASE_CHAIN`
    """
    values = read_yaml_file(path)
    if not isinstance(values, dict):
        raise ValueError(f"{path} must hold a recipe mapping, not {type(values).__name__}")
    values = {"name": path.stem, **values}
    base = values.pop("base", None)
    if base is None:
        return values
    if len(chain) + 1 >= MAX_BASE_CHAIN:
        raise ValueError(f"{chain[0]}: its base: chain is longer than {MAX_BASE_CHAIN} recipes; merge some of them")
    base_path = recipe_path(base, relative_to=path.parent)
    if base_path.resolve() in {p.resolve() for p in (*chain, path)}:
        raise ValueError(f"{path}: base {base!r} makes a cycle of recipes ({' -> '.join(p.name for p in (*chain, path))})")
    inherited = read_recipe_file(base_path, (*chain, path))
    inherited.pop(RUN_KEY, None)  # a base's run options are its own
    return merge_recipe({**inherited, "name": values["name"]}, values)


def load_recipe(recipe: str | os.PathLike[str]) -> Recipe:
    """A shipped recipe by name, or any recipe YAML file by its path, resolved (its ``base:`` chain merged in; a
    ``run:`` section is not part of the recipe: :func:`load_settings` reads it).

    :raises ValueError: an unknown name (the valid ones are listed) or an invalid file
    """
    path = recipe_path(recipe)
    return Recipe.from_dict(read_recipe_file(path), source=path)


def load_settings(recipe: str | os.PathLike[str]) -> TrainSettings:
    """A recipe with its run options: a shipped recipe by name (the default run options), a recipe file with its
    ``run:`` section (a run's ``config.yaml`` included), or a run folder (its ``config.yaml``).

    :raises FileNotFoundError: a folder that is not a run folder
    :raises ValueError: an unknown name (the valid ones are listed) or an invalid file
    """
    if isinstance(recipe, (str, os.PathLike)) and str(recipe) not in recipe_names() and Path(recipe).is_dir():
        path = Path(recipe) / "config.yaml"
        if not path.is_file():
            raise FileNotFoundError(f"{recipe} is not a run folder: {path} is missing")
        try:
            return TrainSettings.from_dict(read_recipe_file(path), path)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{path} holds an invalid recipe: {error}") from None
    path = recipe_path(recipe)
    return TrainSettings.from_dict(read_recipe_file(path), path)


def write_settings(settings: TrainSettings, path: Path) -> None:
    """Write a run's recipe with its run options (:meth:`TrainSettings.to_dict`) atomically as a recipe file: its
    ``config.yaml``."""
    atomic_write(path, yaml.safe_dump(settings.to_dict(), sort_keys=False))


# Options ------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecipeOption:
    """An option of ``sb3-formation train`` and of :func:`layered_settings`: a field of the recipe, of one of its
    sections or of the run options, declared with :func:`~sb3_formation.experiment.sections.option`.

    :param name: the option's name (a keyword of :func:`layered_settings`)
    :param section: the key of the field's section; ``None`` for a field of the recipe itself, ``run`` for a run option
    :param field: the field it sets
    :param hint: the field's type
    :param help: the field's ``:param:`` text
    :param flag: its command-line flag
    :param choices: the values the command line accepts, if only some
    """

    name: str
    section: str | None
    field: str
    hint: Any
    help: str
    flag: str
    choices: tuple[str, ...] | None


@cache
def recipe_options() -> tuple[RecipeOption, ...]:
    """Every option of ``sb3-formation train`` that changes a recipe or a run: the fields declared with
    :func:`~sb3_formation.experiment.sections.option`, the recipe's own, then its sections', then the run options."""
    owners: list[tuple[str | None, type]] = [(None, Recipe), *SECTIONS.items(), (RUN_KEY, RunOptions)]
    options = []
    for section, owner in owners:
        hints, docs = typing.get_type_hints(owner), field_docs(owner)
        for item in fields(owner):
            if OPTION in item.metadata:
                declared = item.metadata[OPTION]
                name = declared["name"] or item.name
                flag = declared["flag"] or "--" + name.replace("_", "-")
                options.append(
                    RecipeOption(name, section, item.name, hints[item.name], docs[item.name], flag, declared["choices"])
                )
    return tuple(options)


def option_changes(options: dict[str, Any]) -> dict[str, Any]:
    """The partial recipe (for :meth:`Recipe.with_changes`) that options of ``sb3-formation train`` give; ``None`` values
    are left out.

    :param options: options of :func:`recipe_options` (run options apart), a section's key with a mapping that merges
        into that section (``ppo={"n_steps": 64}``), or ``agents``: teams of this many agents (the task's ``n_agents``,
        and no ``team_sizes``). A ``minutes`` budget without a ``steps`` one replaces the recipe's steps budget, so that
        the time is the budget; ``recurrent=False`` without a ``cell`` drops the recipe's cell.
    :raises ValueError: an option that changes no recipe
    """
    declared = {item.name: item for item in recipe_options() if item.section != RUN_KEY}
    given = {name: value for name, value in options.items() if value is not None}
    unknown = sorted(set(given) - set(declared) - set(SECTIONS) - {"agents"})
    if unknown:
        raise ValueError(f"unknown recipe option(s) {unknown}; valid: {sorted({*declared, *SECTIONS, 'agents'})}")
    changes: dict[str, Any] = {}
    for name, value in given.items():
        item = declared.get(name)
        if name == "agents":
            continue
        if item is None:  # a section's key
            if not isinstance(value, dict):
                raise ValueError(f"{name} must be a mapping of its keys, got {value!r}")
            changes[name] = {**changes.get(name, {}), **value}
        elif item.section is None:  # a key of the recipe itself
            changes[item.field] = value
        elif item.field == SECTIONS[item.section].rest:  # a section's flat keys
            changes[item.section] = {**changes.get(item.section, {}), **value}
        else:
            changes.setdefault(item.section, {})[item.field] = value
    if "minutes" in given and "steps" not in given:
        changes.setdefault("training", {})["steps"] = None
    if given.get("recurrent") is False and "cell" not in given:
        changes.setdefault("policy", {})["cell"] = None  # an MLP has no cell
    if "agents" in given:
        changes["env"] = {**changes.get("env", {}), "n_agents": given["agents"]}
        changes.setdefault("team_sizes", None)
    return changes


def layered_settings(recipe: str | os.PathLike[str] | None = None, **options: Any) -> TrainSettings:
    """Settings layered as ``sb3-formation train`` layers them: a recipe with its run options (:func:`load_settings`),
    then ``options``.

    :param recipe: a shipped recipe's name or a recipe file (default: :data:`DEFAULT_RECIPE`)
    :param options: run options (fields of :class:`RunOptions`) and recipe changes (:func:`option_changes`: ``env``,
        ``ppo``, ``agents``, ``iterations``, ``n_envs``, ``steps``, ...); ``None`` values are ignored
    :raises ValueError: an unknown option, or invalid values
    """
    settings = load_settings(DEFAULT_RECIPE if recipe is None else recipe)
    run_names = {item.name for item in fields(RunOptions)}
    run = {name: value for name, value in options.items() if name in run_names and value is not None}
    changes = option_changes({name: value for name, value in options.items() if name not in run_names})
    return TrainSettings(settings.recipe.with_changes(changes), settings.run.replace(**run))


def thesis_recipe_for(reward: str | None, n_agents: int | None, team_reward: bool) -> str:
    """The thesis recipe meant by ``--reward``, ``--agents`` and ``--team-reward`` (``docs/design.md``).

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
    return DEFAULT_RECIPE


# What a model file records of its recipe ----------------------------------------------------------------------------


def residual_base(spec: dict[str, Any], config: FormationConfig) -> tuple[Controller, float]:
    """The controller and the correction's bound that a recipe's ``residual`` describes.

    :param spec: ``controller``, ``scale`` and optional ``gains`` (:class:`ResidualSection`)
    :param config: the task the controller acts in
    :raises ValueError: the controller reads the map (a residual policy is decentralised, like its controller)
    """
    controller = controller_from_spec(spec, config)
    if getattr(controller, "privileged", False):
        raise ValueError(
            f"controller {spec['controller']!r} reads the map (privileged): a residual policy's controller must be "
            "decentralised"
        )
    return controller, check_residual_scale(spec["scale"])


def residual_policy(spec: dict[str, Any], correction: TeamPolicy) -> ResidualPolicy:
    """The residual policy of a recipe's ``residual`` with ``correction`` (e.g. a trained model) as its learned part."""
    base, scale = residual_base(spec, correction.config)
    return ResidualPolicy(base, correction, scale)


def with_schedules(kwargs: dict[str, Any]) -> dict[str, Any]:
    """PPO keyword arguments with their schedules written as data (:func:`~sb3_formation.experiment.sections.schedule`)
    turned into SB3 schedules."""
    scheduled = ("learning_rate", "clip_range", "clip_range_vf")
    return {
        name: schedule(value, name) if name in scheduled and value is not None else value for name, value in kwargs.items()
    }
