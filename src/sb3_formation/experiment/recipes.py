"""Recipes: a whole training recipe as one record of data.

A recipe names the task (an environment recipe of :data:`~sb3_formation.env.config.TASKS` and field overrides), the
policy (MLP or recurrent, its cell, a team critic, sigma, action scale, other policy keyword arguments), the PPO
settings, the curriculum (iterations per stage, success threshold), the number of parallel teams and the evaluation
protocol. The thesis's four recipes are YAML files shipped in this package (``sb3_formation/experiment/setups/``), each
line citing its table, equation or section; adding a recipe is adding one such file. A YAML file anywhere can be used
as a recipe by giving its path instead of a name.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import LinearSchedule

from sb3_formation.controllers import CONTROLLERS
from sb3_formation.controllers.base import Controller, TeamPolicy
from sb3_formation.controllers.residual import ResidualPolicy, check_residual_scale
from sb3_formation.env.config import TASKS, FormationConfig
from sb3_formation.sb3.imitation import ImitationSettings
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import CELLS, RecurrentFormationPolicy
from sb3_formation.utils.checks import is_count, is_number
from sb3_formation.utils.deprecation import warn_renamed
from sb3_formation.utils.yaml_files import read_yaml

#: The folder of the shipped recipes, one ``<name>.yaml`` each.
RECIPES_FOLDER = Path(__file__).with_name("shipped_recipes")
#: The recipe used when none is named.
DEFAULT_RECIPE = "ch5-bearing"
#: Keys of a recipe's ``policy:`` that choose the network rather than being passed to it.
_POLICY_CHOICES = ("recurrent", "cell", "team_critic")


@dataclass(frozen=True)
class Recipe:
    """One training recipe (see the module docstring); every field is plain YAML data.

    :param name: the recipe's name (its file's stem)
    :param description: one line for ``sb3-formation recipes``
    :param env: ``task`` (a name of :data:`~sb3_formation.env.config.TASKS`) and any :class:`FormationConfig` fields
        overriding it
    :param policy: ``recurrent`` (bool), ``cell`` (``gru``/``lstm``, recurrent only), ``team_critic`` (bool; unset:
        with the team reward, fig. 4.3), and keyword arguments of the policy class (``sigma``, ``action_scale``, ...)
    :param ppo: keyword arguments of ``PPO`` (``n_steps``, ``batch_size``, ``learning_rate``, ...)
    :param curriculum: ``iterations`` (PPO iterations of stages 1, 2, 3) and ``success_threshold`` (or null)
    :param n_envs: parallel teams during training (each team is one env of the VecEnv, its agents the env's slots)
    :param team_sizes: optional: teams of several sizes in one rollout, taken in turn (team j has
        ``team_sizes[j % len(team_sizes)]`` agents; :class:`~sb3_formation.sb3.vec_env.FormationVecEnv`); without it
        every team has the task's ``n_agents``. A policy trained on several sizes acts in teams of any size
    :param evaluation: ``episodes`` and ``stage`` of the evaluation protocol
    :param training: optional training features (:data:`TRAINING_DEFAULTS`): ``normalize_reward`` (divide rewards by
        a running std of the discounted return, SB3's ``VecNormalize``), ``center_observations`` (subtract the running
        mean of the observations too, unlike thesis 3.1.4: ``ScaleNormalizeVecEnv(center=True)``), ``steps`` (a budget
        of agent-steps, split between the stages in the curriculum's proportions), ``eval_every`` and
        ``eval_episodes`` (periodic evaluation)
    :param residual: optional: train a correction of a controller (``controller``: a name of
        :data:`~sb3_formation.controllers.CONTROLLERS`, ``gains``: its keyword arguments, ``scale``: the correction's
        bound as a fraction of F_max); the env then receives ``clip(a_controller + scale * a_policy, -1, 1)``
    :param imitation: optional: pretrain the actor on a controller's actions before PPO (``controller``, ``gains``,
        and the fields of :class:`~sb3_formation.sb3.imitation.ImitationSettings`: rounds, steps, epochs, batch_size,
        learning_rate, critic_warmup)
    :param source: the file it was read from
    """

    name: str
    description: str
    env: dict[str, Any]
    policy: dict[str, Any]
    ppo: dict[str, Any]
    curriculum: dict[str, Any]
    n_envs: int
    evaluation: dict[str, Any]
    training: dict[str, Any] = field(default_factory=dict)
    residual: dict[str, Any] = field(default_factory=dict)
    imitation: dict[str, Any] = field(default_factory=dict)
    team_sizes: list[int] | None = None
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        where = f"recipe {self.name!r}"
        if self.env.get("task") not in TASKS:
            raise ValueError(f"{where}: env: task must be one of {sorted(TASKS)}, got {self.env.get('task')!r}")
        self.config()  # validates the env overrides
        iterations = self.curriculum.get("iterations")
        valid = isinstance(iterations, (list, tuple)) and len(iterations) == 3 and all(is_count(i) for i in iterations)
        if not valid or sum(iterations) < 1:
            raise ValueError(f"{where}: curriculum: iterations must be three integers >= 0, not all 0, got {iterations!r}")
        unknown = sorted(set(self.curriculum) - {"iterations", "success_threshold"})
        if unknown:
            raise ValueError(f"{where}: unknown curriculum keys {unknown}; valid: iterations, success_threshold")
        unknown = sorted(set(self.training) - set(TRAINING_DEFAULTS))
        if unknown:
            raise ValueError(f"{where}: unknown training keys {unknown}; valid: {list(TRAINING_DEFAULTS)}")
        for name in ("normalize_reward", "center_observations"):
            if not isinstance(self.training_option(name), bool):
                raise ValueError(f"{where}: training: {name} must be true or false")
        for name in ("steps", "eval_every", "eval_episodes"):
            value = self.training_option(name)
            if value is not None and not (is_count(value) and value >= 1):
                raise ValueError(f"{where}: training: {name} must be an integer >= 1 or null, got {value!r}")
        for name in ("learning_rate", "clip_range", "clip_range_vf"):
            if self.ppo.get(name) is not None:
                schedule(self.ppo[name], f"{where}: ppo: {name}")
        if not (is_count(self.n_envs) and self.n_envs >= 1):
            raise ValueError(f"{where}: n_envs must be an integer >= 1, got {self.n_envs!r}")
        unknown = sorted(set(self.evaluation) - {"episodes", "stage"})
        if unknown or not (is_count(self.evaluation.get("episodes")) and self.evaluation["episodes"] >= 1):
            raise ValueError(f"{where}: evaluation needs episodes (>= 1) and may give stage, got {self.evaluation!r}")
        team_critic = self.policy.get("team_critic")
        if not isinstance(self.policy.get("recurrent", False), bool) or team_critic not in (None, True, False):
            raise ValueError(f"{where}: policy: recurrent must be true or false, team_critic true, false or unset")
        self.ppo_kwargs()  # validates the policy choices
        if self.team_sizes is not None:
            sizes = self.team_sizes
            if not (isinstance(sizes, list) and sizes and all(is_count(size) for size in sizes)):
                raise ValueError(f"{where}: team_sizes must be a non-empty list of team sizes, got {sizes!r}")
            if "team_size" in self.ppo_kwargs()["policy_kwargs"] and len(set(sizes)) > 1:
                raise ValueError(f"{where}: a team critic reads teams of one size; team_sizes lists {sizes}")
            for size in sizes:
                try:
                    self.config(n_agents=size)
                except ValueError as error:
                    raise ValueError(f"{where}: team_sizes: {error}") from error
        if self.residual:
            unknown = sorted(set(self.residual) - {"controller", "gains", "scale"})
            if unknown or "controller" not in self.residual or "scale" not in self.residual:
                raise ValueError(f"{where}: residual needs controller and scale and may give gains, got {self.residual!r}")
            try:
                residual_base(self.residual, self.config())
            except (TypeError, ValueError) as error:
                raise ValueError(f"{where}: residual: {error}") from error
        if self.imitation:
            if self.recurrent or self.residual:
                raise ValueError(f"{where}: imitation pretrains an MLP actor of whole actions: not recurrent, not residual")
            try:
                self.imitation_settings()
                self.teacher(self.config())
            except (TypeError, ValueError) as error:
                raise ValueError(f"{where}: imitation: {error}") from error

    @property
    def recurrent(self) -> bool:
        """Whether the recipe's policy is recurrent."""
        return bool(self.policy.get("recurrent", False))

    def imitation_settings(self) -> ImitationSettings | None:
        """How the actor is pretrained before PPO (``None`` without an ``imitation`` block)."""
        if not self.imitation:
            return None
        settings = {key: value for key, value in self.imitation.items() if key not in ("controller", "gains")}
        unknown = sorted(set(settings) - set(ImitationSettings.__dataclass_fields__))
        if unknown or "controller" not in self.imitation:
            raise ValueError(
                f"the imitation block needs controller and may give gains and {list(ImitationSettings.__dataclass_fields__)}; "
                f"unknown: {unknown}"
            )
        return ImitationSettings(**settings)

    def teacher(self, config: FormationConfig) -> Controller | None:
        """The controller the actor imitates before PPO (``None`` without an ``imitation`` block).

        :param config: the task the controller acts in
        """
        return controller_from_spec(self.imitation, config) if self.imitation else None

    def training_option(self, name: str) -> Any:
        """A training feature's value: the recipe's, else its default (:data:`TRAINING_DEFAULTS`)."""
        return self.training.get(name, TRAINING_DEFAULTS[name])

    @property
    def iterations(self) -> tuple[int, int, int]:
        """PPO iterations of curriculum stages 1, 2 and 3."""
        return tuple(int(value) for value in self.curriculum["iterations"])

    @property
    def success_threshold(self) -> float | None:
        """Rolling success rate that ends stages 1-2 early, or ``None``."""
        return self.curriculum.get("success_threshold")

    def config(self, **overrides: Any) -> FormationConfig:
        """The recipe's task configuration, with ``overrides`` (:class:`FormationConfig` fields) applied."""
        env = {name: value for name, value in self.env.items() if name != "task"}
        if "stage_disabled_terms" in env:
            env["stage_disabled_terms"] = tuple(tuple(terms) for terms in env["stage_disabled_terms"])
        return FormationConfig.task(self.env["task"], **{**env, **overrides})

    def ppo_kwargs(
        self, config: FormationConfig | None = None, recurrent: bool | None = None, cell: str | None = None
    ) -> dict:
        """Keyword arguments of ``PPO`` (or, for a recurrent policy, :class:`RecurrentFormationPPO`).

        :param config: the run's task (default: the recipe's); a team critic reads its team size, and without
            ``team_critic`` in the recipe the critic is the team critic exactly when the task uses the team reward
        :param recurrent: override the recipe's choice of a recurrent policy
        :param cell: override the recurrent cell
        """
        config = self.config() if config is None else config
        recurrent = self.recurrent if recurrent is None else recurrent
        team_critic = self.policy.get("team_critic")
        team_critic = config.team_reward if team_critic is None else team_critic
        policy_kwargs = {name: value for name, value in self.policy.items() if name not in _POLICY_CHOICES}
        if recurrent:
            if team_critic:
                raise ValueError(
                    f"{self.name} uses the team critic, which has no recurrent version: train it without recurrent"
                )
            cell = cell or self.policy.get("cell") or "gru"
            if cell not in CELLS:
                raise ValueError(f"cell must be one of {CELLS}, got {cell!r}")
            return {"policy": RecurrentFormationPolicy, **self.ppo, "policy_kwargs": {**policy_kwargs, "cell": cell}}
        if team_critic:
            policy_kwargs["team_size"] = config.n_agents
        return {"policy": FormationPolicy, **self.ppo, "policy_kwargs": policy_kwargs}

    @classmethod
    def from_dict(cls, name: str, values: dict[str, Any], source: Path | None = None) -> Recipe:
        """A recipe from its YAML mapping; unknown or missing keys are errors that name the valid ones."""
        keys = [f.name for f in fields(cls) if f.name not in ("name", "source")]
        if not isinstance(values, dict):
            raise ValueError(f"recipe {name!r} must be a mapping of {keys}, not {type(values).__name__}")
        values = _with_current_keys(values, name)
        required = [key for key in keys if key not in ("training", "residual", "imitation", "team_sizes")]
        unknown, missing = sorted(set(values) - set(keys)), [key for key in required if key not in values]
        if unknown or missing:
            raise ValueError(f"recipe {name!r}: unknown keys {unknown}, missing keys {missing}; a recipe has {keys}")
        return cls(name=name, source=source, **values)


def _with_current_keys(values: dict[str, Any], name: str) -> dict[str, Any]:
    """A recipe mapping with the keys of earlier releases renamed, each with a warning: ``teams`` -> ``n_envs``, and
    ``env: preset`` -> ``env: task``."""
    values = dict(values)
    if "teams" in values and "n_envs" not in values:
        warn_renamed(f"the key teams: of recipe {name!r}", "n_envs:", stacklevel=4)
        values["n_envs"] = values.pop("teams")
    env = values.get("env")
    if isinstance(env, dict) and "preset" in env and "task" not in env:
        warn_renamed(f"the key env: preset: of recipe {name!r}", "env: task:", stacklevel=4)
        values["env"] = {("task" if key == "preset" else key): value for key, value in env.items()}
    return values


def controller_from_spec(spec: dict[str, Any], config: FormationConfig) -> Controller:
    """The controller a recipe block names (``controller`` and optional ``gains``), acting in ``config``."""
    name = spec["controller"]
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; controllers: {', '.join(sorted(CONTROLLERS))}")
    gains = spec.get("gains") or {}
    if not isinstance(gains, dict):
        raise ValueError(f"gains must be a mapping of gain names to values, got {gains!r}")
    return CONTROLLERS[name](config, **gains)


def residual_base(spec: dict[str, Any], config: FormationConfig) -> tuple[Controller, float]:
    """The controller and the correction's bound that a recipe's ``residual`` describes.

    :param spec: ``controller``, ``scale`` and optional ``gains`` (see :class:`Recipe`)
    :param config: the task the controller acts in
    """
    return controller_from_spec(spec, config), check_residual_scale(spec["scale"])


def residual_policy(spec: dict[str, Any], correction: TeamPolicy) -> ResidualPolicy:
    """The residual policy of a recipe's ``residual`` with ``correction`` (e.g. a trained model) as its learned part."""
    base, scale = residual_base(spec, correction.config)
    return ResidualPolicy(base, correction, scale)


#: Training features a recipe may switch on, and their defaults (the thesis's: none of them).
TRAINING_DEFAULTS: dict[str, Any] = {
    "normalize_reward": False,
    "center_observations": False,
    "steps": None,
    "eval_every": None,
    "eval_episodes": 20,
}


def schedule(value: Any, where: str = "schedule") -> float | Schedule:
    """A learning rate or clip range written as data: a number (constant), or ``{start: a, end: b}`` for a linear change
    from a at the start of training to b at its end (over the run's budget).

    :param value: the data
    :param where: what it is, for the error message
    :raises ValueError: neither form, or not finite and > 0
    """
    if isinstance(value, dict) and set(value) == {"start", "end"}:
        start, end = (value[key] for key in ("start", "end"))
        if all(is_number(v) and v > 0 for v in (start, end)):
            return LinearSchedule(float(start), float(end), 1.0)
    elif is_number(value) and value > 0:
        return float(value)
    raise ValueError(f"{where} must be a number > 0 or {{start: a, end: b}} with numbers > 0, got {value!r}")


def with_schedules(kwargs: dict[str, Any]) -> dict[str, Any]:
    """PPO keyword arguments with their schedules written as data (:func:`schedule`) turned into SB3 schedules."""
    scheduled = ("learning_rate", "clip_range", "clip_range_vf")
    return {
        name: schedule(value, name) if name in scheduled and value is not None else value for name, value in kwargs.items()
    }


def recipe_names() -> list[str]:
    """Names of the recipes shipped with the package."""
    return sorted(path.stem for path in RECIPES_FOLDER.glob("*.yaml"))


def load_recipe(name: str | os.PathLike[str]) -> Recipe:
    """A shipped recipe by name, or any recipe YAML file by its path.

    :raises ValueError: an unknown name (the valid ones are listed) or an invalid file
    """
    if not isinstance(name, (str, os.PathLike)):
        raise ValueError(f"recipe must be a recipe name or the path of a recipe YAML file, got {name!r}")
    path = Path(name)
    if path.suffix not in (".yaml", ".yml"):
        if str(name) not in recipe_names():
            raise ValueError(f"unknown recipe {str(name)!r}; recipes: {', '.join(recipe_names())}, or a recipe YAML file")
        path = RECIPES_FOLDER / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"no recipe file {path}")
    values = read_yaml(path.read_text(), str(path))
    return Recipe.from_dict(path.stem, values, source=path)


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
