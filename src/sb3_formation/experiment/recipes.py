"""Recipes: a whole training recipe as one record of data, in one YAML format.

A recipe names the task (a name of :data:`~sb3_formation.env.config.TASKS` and field overrides), the policy (MLP or
recurrent, its cell, a team critic, sigma, action scale, other policy keyword arguments), the PPO settings, the
curriculum (iterations per stage, success threshold), the budget, the number of parallel teams and the evaluation
protocol. The same format serves the recipes shipped in this package (``sb3_formation/experiment/shipped_recipes/``,
each line citing its table, equation or section), a user's file, the experiments under ``experiments/`` and a run's
own ``config.yaml``, which is the complete recipe the run trained (:meth:`Recipe.to_dict`): ``sb3-formation train
--config runs/X/config.yaml --seed 1`` trains it again.

A recipe file may name a ``base:`` recipe (a shipped name, or a path relative to the file) and give only what differs:
its sections merge into the base's key by key (:func:`merge_recipe`), as RL Zoo's YAML anchors do. :func:`load_recipe`
resolves the chain once into a frozen :class:`Recipe`. The options of a run that are not the recipe (seed, device,
workers, folders, checkpoints, progress) are :class:`~sb3_formation.experiment.settings.RunOptions`, written beside
the recipe under ``run:``.
"""

from __future__ import annotations

import dataclasses
import inspect
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, cast

from stable_baselines3 import PPO
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import LinearSchedule

from sb3_formation.controllers import controller_from_spec
from sb3_formation.controllers.base import Controller, TeamPolicy
from sb3_formation.controllers.residual import ResidualPolicy, check_residual_scale
from sb3_formation.env.config import TASKS, FormationConfig
from sb3_formation.env.observations import observation_fields
from sb3_formation.safety.filter import SafetyGains
from sb3_formation.sb3.imitation import ImitationSettings
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import CELLS, RecurrentFormationPolicy
from sb3_formation.utils.checks import check_name, is_count, is_number
from sb3_formation.utils.deprecation import warn_renamed
from sb3_formation.utils.yaml_files import read_yaml_file

#: The folder of the shipped recipes, one ``<name>.yaml`` each.
RECIPES_FOLDER = Path(__file__).with_name("shipped_recipes")
#: The recipe used when none is named.
DEFAULT_RECIPE = "ch5-bearing"
#: The key of a recipe file that holds the run options of an experiment or a run, not the recipe.
RUN_KEY = "run"
#: The sections of a recipe: mappings that a derived recipe merges key by key (:func:`merge_recipe`).
SECTIONS = ("env", "policy", "ppo", "curriculum", "evaluation", "training", "residual", "imitation", "safety")
#: Keys of a recipe's ``evaluation:`` (arguments of :func:`~sb3_formation.experiment.evaluation.evaluate`).
EVALUATION_KEYS = ("episodes", "stage", "seed", "n_envs", "deterministic", "record")
#: Keys of a recipe's ``policy:`` that choose the network rather than being passed to it.
_POLICY_CHOICES = ("recurrent", "cell", "team_critic")
#: Keyword arguments of SB3's ``PPO`` that a recipe's ``ppo:`` may give (what the run, the env and ``policy:`` set
#: are not among them).
PPO_KEYS = frozenset(inspect.signature(PPO.__init__).parameters) - {
    "self",
    "policy",
    "env",
    "policy_kwargs",
    "seed",
    "device",
    "verbose",
    "tensorboard_log",
    "_init_setup_model",
}
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
#: Training features a recipe may switch on, and their defaults (the thesis's: none of them).
TRAINING_DEFAULTS: dict[str, Any] = {
    "normalize_reward": False,
    "center_observations": False,
    "steps": None,
    "minutes": None,
    "eval_every": None,
    "eval_episodes": 20,
}
#: Options of ``sb3-formation train`` that change a recipe, and where each goes in it: (section or None, key).
RECIPE_OPTIONS: dict[str, tuple[str | None, str]] = {
    "iterations": ("curriculum", "iterations"),
    "success_threshold": ("curriculum", "success_threshold"),
    "n_envs": (None, "n_envs"),
    "team_sizes": (None, "team_sizes"),
    "recurrent": ("policy", "recurrent"),
    "cell": ("policy", "cell"),
    "steps": ("training", "steps"),
    "minutes": ("training", "minutes"),
    "normalize_reward": ("training", "normalize_reward"),
    "eval_every": ("training", "eval_every"),
}


@dataclass(frozen=True)
class Recipe:
    """One training recipe (see the module docstring), resolved: its ``base:`` merged in, every field plain YAML data.

    :param name: the recipe's name (its ``name:`` key, else its file's stem)
    :param description: one line for ``sb3-formation recipes``
    :param env: ``task`` (a name of :data:`~sb3_formation.env.config.TASKS`) and any :class:`FormationConfig` fields
        overriding it
    :param policy: ``recurrent`` (bool), ``cell`` (``gru``/``lstm``, recurrent only), ``team_critic`` (bool; unset:
        with the team reward, fig. 4.3), and keyword arguments of the policy class (``sigma``, ``action_scale``, ...)
    :param ppo: keyword arguments of ``PPO`` (``n_steps``, ``batch_size``, ``learning_rate``, ...)
    :param curriculum: ``iterations`` (PPO iterations of stages 1, 2, 3; with a budget in ``training``, their
        proportions) and ``success_threshold`` (or null)
    :param n_envs: parallel teams during training (each team is one env of the VecEnv, its agents the env's slots)
    :param evaluation: the evaluation protocol: ``episodes`` and ``stage``, and optionally ``seed``, ``n_envs``,
        ``deterministic`` and ``record`` (arguments of :func:`~sb3_formation.experiment.evaluation.evaluate`)
    :param training: optional training features (:data:`TRAINING_DEFAULTS`): ``normalize_reward`` (divide rewards by
        a running std of the discounted return, SB3's ``VecNormalize``), ``center_observations`` (subtract the running
        mean of the observations too, unlike thesis 3.1.4: ``ScaleNormalizeVecEnv(center=True)``), the budget
        (``steps`` of agents, ``minutes`` of wall-clock; see :meth:`stage_iterations`), ``eval_every`` and
        ``eval_episodes`` (periodic evaluation)
    :param residual: optional: train a correction of a controller (``controller``: a name of
        :data:`~sb3_formation.controllers.CONTROLLERS`, ``gains``: its keyword arguments, ``scale``: the correction's
        bound as a fraction of F_max); the env then receives ``clip(a_controller + scale * a_policy, -1, 1)``
    :param imitation: optional: pretrain the actor on a controller's actions before PPO (``controller``, ``gains``,
        and the fields of :class:`~sb3_formation.sb3.imitation.ImitationSettings`: rounds, steps, epochs, batch_size,
        learning_rate, critic_warmup)
    :param safety: optional: train behind the safety filter ("shielded" PPO, ``docs/safety.md``): the env applies the
        filtered action, PPO keeps its own. ``penalty`` (>= 0, default 0) subtracts ``penalty |a_safe - a|`` from each
        agent's reward, and any field of :class:`~sb3_formation.safety.filter.SafetyGains` sets the filter's gains; a
        non-empty section turns the filter on (``safety: {penalty: 0}`` with the default gains). The trained policy acts
        behind the same filter wherever it is loaded or exported
    :param team_sizes: optional: teams of several sizes in one rollout, taken in turn (team j has
        ``team_sizes[j % len(team_sizes)]`` agents; :class:`~sb3_formation.sb3.vec_env.FormationVecEnv`); without it
        every team has the task's ``n_agents`` (:attr:`sizes`). A policy trained on several sizes acts in teams of any
        size
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
    safety: dict[str, Any] = field(default_factory=dict)
    team_sizes: list[int] | None = None
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        where = f"recipe {self.name!r}"
        if not isinstance(self.name, str):
            raise ValueError(f"{where}: its name must be text")
        check_name(self.name, "recipe name")  # it begins the name of a run's folder under --logdir
        for section in SECTIONS:
            if not isinstance(getattr(self, section), dict):
                raise ValueError(f"{where}: {section} must be a mapping, got {getattr(self, section)!r}")
        if self.env.get("task") not in TASKS:
            raise ValueError(f"{where}: env: task must be one of {sorted(TASKS)}, got {self.env.get('task')!r}")
        self.config()  # validates the env overrides
        iterations: Any = self.curriculum.get("iterations")
        valid = isinstance(iterations, (list, tuple)) and len(iterations) == 3 and all(is_count(i) for i in iterations)
        if not valid or sum(iterations) < 1:
            raise ValueError(f"{where}: curriculum: iterations must be three integers >= 0, not all 0, got {iterations!r}")
        unknown = sorted(set(self.curriculum) - {"iterations", "success_threshold"})
        if unknown:
            raise ValueError(f"{where}: unknown curriculum keys {unknown}; valid: iterations, success_threshold")
        threshold = self.success_threshold
        if threshold is not None and not (is_number(threshold) and 0 <= threshold <= 1):
            raise ValueError(f"{where}: curriculum: success_threshold must be a number in [0, 1] or null, got {threshold!r}")
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
        minutes = self.training_option("minutes")
        if minutes is not None and not (is_number(minutes) and minutes > 0):
            raise ValueError(f"{where}: training: minutes must be a finite number > 0 or null, got {minutes!r}")
        if not (is_count(self.n_envs) and self.n_envs >= 1):
            raise ValueError(f"{where}: n_envs must be an integer >= 1, got {self.n_envs!r}")
        unknown = sorted(set(self.evaluation) - set(EVALUATION_KEYS))
        if unknown or not (is_count(self.evaluation.get("episodes")) and self.evaluation["episodes"] >= 1):
            raise ValueError(
                f"{where}: evaluation needs episodes (>= 1) and may give {', '.join(EVALUATION_KEYS[1:])}, "
                f"got {self.evaluation!r}"
            )
        team_critic = self.policy.get("team_critic")
        if not isinstance(self.policy.get("recurrent", False), bool) or team_critic not in (None, True, False):
            raise ValueError(f"{where}: policy: recurrent must be true or false, team_critic true, false or unset")
        if self.policy.get("cell") is not None and not self.recurrent:
            raise ValueError(f"{where}: policy: cell {self.policy['cell']!r} applies to recurrent policies only")
        valid_keys = PPO_KEYS | ({"max_sequence_length"} if self.recurrent else set())
        unknown = sorted(set(self.ppo) - valid_keys)
        if unknown:
            hint = "; policy keyword arguments go under policy:" if "policy_kwargs" in unknown else ""
            raise ValueError(f"{where}: unknown ppo settings {unknown}; valid: {sorted(valid_keys)}{hint}")
        for name in ("learning_rate", "clip_range", "clip_range_vf"):
            if self.ppo.get(name) is not None:
                schedule(self.ppo[name], f"{where}: ppo: {name}")
        for name in ("n_steps", "n_epochs"):
            if name in self.ppo and not (is_count(self.ppo[name]) and self.ppo[name] >= 1):
                raise ValueError(f"{where}: ppo: {name} must be an integer >= 1, got {self.ppo[name]!r}")
        if "batch_size" in self.ppo and not (is_count(self.ppo["batch_size"]) and self.ppo["batch_size"] >= 2):
            raise ValueError(  # SB3 normalises the advantages over each mini-batch: one sample has no spread
                f"{where}: ppo: batch_size must be an integer >= 2 (advantages are normalised over a mini-batch), "
                f"got {self.ppo['batch_size']!r}"
            )
        for name, low_open in (("gamma", True), ("gae_lambda", False)):
            value = self.ppo.get(name)
            if value is not None and not (is_number(value) and (0 < value <= 1 if low_open else 0 <= value <= 1)):
                bounds = "(0, 1]" if low_open else "[0, 1]"
                raise ValueError(f"{where}: ppo: {name} must be a number in {bounds}, got {value!r}")
        self.ppo_kwargs()  # validates the policy choices
        if self.team_sizes is not None:
            sizes = self.team_sizes
            if not (isinstance(sizes, (list, tuple)) and sizes and all(is_count(size) for size in sizes)):
                raise ValueError(f"{where}: team_sizes must be a non-empty list of team sizes, got {sizes!r}")
            for size in sizes:
                try:
                    self.config(n_agents=size)
                except ValueError as error:
                    raise ValueError(f"{where}: team_sizes: {error}") from error
        if "team_size" in self.ppo_kwargs()["policy_kwargs"] and set(self.sizes) != {self.config().n_agents}:
            raise ValueError(
                f"{where}: a team critic reads teams of n_agents={self.config().n_agents}; team_sizes lists {self.sizes}"
            )
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
        if self.safety:
            try:
                self.safety_gains()
            except ValueError as error:
                raise ValueError(f"{where}: safety: {error}") from error
            penalty = self.safety_penalty
            if not (is_number(penalty) and penalty >= 0):
                raise ValueError(f"{where}: safety: penalty must be a finite number >= 0, got {penalty!r}")
        self.stage_iterations()  # validates the budget against the curriculum
        if self.n_envs > MAX_TEAMS:
            raise ValueError(f"{where}: n_envs must be at most {MAX_TEAMS} (teams played at once), got {self.n_envs}")
        features = max(sum(field.size for field in observation_fields(self.config(n_agents=n))) for n in self.sizes)
        rollout = self.steps_per_iteration() * (features + ROLLOUT_VALUES) * 4  # float32
        if rollout > MAX_ROLLOUT_BYTES:
            raise ValueError(
                f"{where}: a PPO iteration of n_steps={self.ppo_kwargs().get('n_steps', PPO_DEFAULT_N_STEPS)} in "
                f"{self.n_envs} teams would hold {rollout / 2**30:.1f} GiB of rollout, beyond the limit of "
                f"{MAX_ROLLOUT_BYTES / 2**30:g} GiB: lower ppo: n_steps or n_envs"
            )

    # Reading and writing ----------------------------------------------------------------------------------------------

    @classmethod
    def from_dict(cls, name: str, values: dict[str, Any], source: Path | None = None) -> Recipe:
        """A recipe from its YAML mapping (its ``base:`` already merged in, see :func:`load_recipe`); unknown or missing
        keys are errors that name the valid ones. A ``name:`` key replaces ``name``; a ``run:`` block (the run options
        of an experiment, :class:`~sb3_formation.experiment.settings.RunOptions`) is not part of the recipe."""
        keys = [f.name for f in fields(cls) if f.name not in ("name", "source")]
        if not isinstance(values, dict):
            raise ValueError(f"recipe {name!r} must be a mapping of {keys}, not {type(values).__name__}")
        values = _with_current_keys(values, name)
        values = {key: value for key, value in values.items() if key != RUN_KEY}
        name = values.pop("name", name)
        if not isinstance(name, str) or not name:
            raise ValueError(f"a recipe's name must be a non-empty string, got {name!r}")
        for section in ("training", "residual", "imitation", "safety"):
            if values.get(section, {}) is None:  # a derived recipe switches a block off with null
                values[section] = {}
        required = [key for key in keys if key not in ("training", "residual", "imitation", "safety", "team_sizes")]
        unknown, missing = sorted(set(values) - set(keys)), [key for key in required if key not in values]
        if unknown or missing:
            raise ValueError(f"recipe {name!r}: unknown keys {unknown}, missing keys {missing}; a recipe has {keys}")
        return cls(name=name, source=source, **values)

    def to_dict(self) -> dict[str, Any]:
        """The complete recipe as plain YAML data: every env field, every training feature, the policy's choices and
        the team sizes resolved. Read back (:meth:`from_dict`) it writes the same mapping again and does not depend on the
        shipped recipes or the task defaults it was made from; a run writes it as its ``config.yaml``."""
        policy = {name: value for name, value in self.policy.items() if name != "cell"}
        policy |= {"recurrent": self.recurrent, "team_critic": self.team_critic}
        if self.recurrent:
            policy["cell"] = self.cell
        return _plain(
            {
                "name": self.name,
                "description": self.description,
                "env": {"task": self.env["task"], **self.config().to_dict()},
                "policy": policy,
                "ppo": self.ppo,
                "curriculum": {"iterations": list(self.iterations), "success_threshold": self.success_threshold},
                "n_envs": self.n_envs,
                "team_sizes": self.sizes,
                "evaluation": self.evaluation,
                "training": {name: self.training_option(name) for name in TRAINING_DEFAULTS},
                "residual": self.residual,
                "imitation": self.imitation,
                "safety": self.safety,
            }
        )

    def with_changes(self, changes: dict[str, Any]) -> Recipe:
        """This recipe with ``changes`` (a partial recipe mapping) merged in as a ``base:`` merges a file
        (:func:`merge_recipe`), e.g. ``{"n_envs": 2, "env": {"max_steps": 60}}``; the result is validated."""
        if not changes:
            return self
        values = merge_recipe(dataclasses.asdict(self), changes)
        values.pop("source")
        return Recipe.from_dict(self.name, values, source=self.source)

    # What the recipe means --------------------------------------------------------------------------------------------

    @property
    def recurrent(self) -> bool:
        """Whether the recipe's policy is recurrent."""
        return bool(self.policy.get("recurrent", False))

    @property
    def cell(self) -> str | None:
        """The recurrent cell (``None`` for an MLP)."""
        return (self.policy.get("cell") or "gru") if self.recurrent else None

    @property
    def team_critic(self) -> bool:
        """Whether the critic reads the whole team (fig. 4.3): as the recipe says, else exactly with the team reward."""
        choice = self.policy.get("team_critic")
        return self.config().team_reward if choice is None else bool(choice)

    @property
    def sizes(self) -> list[int]:
        """The team sizes taken in turn: ``team_sizes``, else the task's ``n_agents``."""
        return [int(size) for size in self.team_sizes] if self.team_sizes is not None else [self.config().n_agents]

    @property
    def iterations(self) -> tuple[int, int, int]:
        """The curriculum's iterations of stages 1, 2 and 3 (with a budget, their proportions)."""
        return cast("tuple[int, int, int]", tuple(int(value) for value in self.curriculum["iterations"]))  # three: validated

    @property
    def success_threshold(self) -> float | None:
        """Rolling success rate that ends stages 1-2 early, or ``None``."""
        return self.curriculum.get("success_threshold")

    def training_option(self, name: str) -> Any:
        """A training feature's value: the recipe's, else its default (:data:`TRAINING_DEFAULTS`)."""
        return self.training.get(name, TRAINING_DEFAULTS[name])

    def config(self, **overrides: Any) -> FormationConfig:
        """The recipe's task configuration, with ``overrides`` (:class:`FormationConfig` fields) applied."""
        env = {name: value for name, value in self.env.items() if name != "task"}
        return FormationConfig.task(self.env["task"], **{**env, **overrides})

    def ppo_kwargs(self, recurrent: bool | None = None, cell: str | None = None) -> dict:
        """Keyword arguments of ``PPO`` (or, for a recurrent policy, :class:`RecurrentFormationPPO`), with the policy
        class and its keyword arguments; a team critic reads the task's team size.

        :param recurrent: override the recipe's choice of a recurrent policy (``--recurrent``/``--no-recurrent``)
        :param cell: override the recurrent cell (``--cell``)
        """
        if recurrent is not None or cell is not None:
            return self.with_changes(recipe_changes(recurrent=recurrent, cell=cell)).ppo_kwargs()
        policy_kwargs = {name: value for name, value in self.policy.items() if name not in _POLICY_CHOICES}
        if self.recurrent:
            if self.team_critic:
                raise ValueError(f"{self.name} uses the team critic, which has no recurrent version: set recurrent: false")
            if self.cell not in CELLS:
                raise ValueError(f"cell must be one of {CELLS}, got {self.cell!r}")
            return {"policy": RecurrentFormationPolicy, **self.ppo, "policy_kwargs": {**policy_kwargs, "cell": self.cell}}
        if self.team_critic:
            policy_kwargs["team_size"] = self.config().n_agents
        return {"policy": FormationPolicy, **self.ppo, "policy_kwargs": policy_kwargs}

    def steps_per_iteration(self) -> int:
        """Agent-steps of one PPO iteration: n_steps in every slot (the agents of every team)."""
        sizes = self.sizes  # team j has sizes[j % len(sizes)] agents
        return self.ppo_kwargs().get("n_steps", PPO_DEFAULT_N_STEPS) * sum(
            sizes[team % len(sizes)] for team in range(self.n_envs)
        )

    def stage_iterations(self) -> tuple[int, int, int | None]:
        """PPO iterations of stages 1, 2 and 3 as trained. Without a budget, the curriculum's iterations. With a
        ``steps`` budget, its iterations (rounded up) split in the curriculum's proportions (stage 3 gets what stages
        1-2 leave); a ``minutes`` budget beside it ends training early if it runs out first. With a ``minutes`` budget
        alone, stage 3 is open-ended (``None``): stages 1-2 end at their shares of the time
        (:meth:`stage_time_shares`), stage 3 when the time is up."""
        budget = self.training_option("steps")
        if budget is None:
            if self.training_option("minutes") is not None:
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
        minutes = self.training_option("minutes")
        return None if minutes is None else 60.0 * minutes

    def safety_gains(self) -> SafetyGains | None:
        """The safety filter's gains of a shielded recipe (:func:`safety_gains`), else ``None``."""
        return safety_gains(self.safety)

    @property
    def safety_penalty(self) -> float:
        """The reward penalty per unit of the filter's change of an action (``safety: penalty``, default 0)."""
        return self.safety.get("penalty", 0.0)

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


def merge_recipe(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``changes`` over ``base``, as a ``base:`` key merges a recipe file: the sections (``env``, ``policy``, ``ppo``,
    ``curriculum``, ``evaluation``, ``training``, ``residual``, ``imitation``) merge key by key; every other value, and
    every value inside a section, replaces the base's (lists and ``net_arch`` whole).

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


def _plain(value: Any) -> Any:
    """Tuples to lists, recursively, so that YAML writes plain lists."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


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


def safety_gains(section: dict[str, Any] | None) -> SafetyGains | None:
    """The safety filter's gains that a recipe's ``safety`` section gives (the section without ``penalty``), or ``None``
    for an empty section (no filter).

    :raises ValueError: an unknown or invalid gain
    """
    if not section:
        return None
    return SafetyGains.from_dict({name: value for name, value in section.items() if name != "penalty"})


def residual_base(spec: dict[str, Any], config: FormationConfig) -> tuple[Controller, float]:
    """The controller and the correction's bound that a recipe's ``residual`` describes.

    :param spec: ``controller``, ``scale`` and optional ``gains`` (see :class:`Recipe`)
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


#: The longest ``base:`` chain a recipe file may have (the shipped recipes are at most 3 deep).
MAX_BASE_CHAIN = 32


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


def load_recipe(name: str | os.PathLike[str]) -> Recipe:
    """A shipped recipe by name, or any recipe YAML file by its path, resolved (its ``base:`` chain merged in).

    :raises ValueError: an unknown name (the valid ones are listed) or an invalid file
    """
    path = recipe_path(name)
    return Recipe.from_dict(path.stem, read_recipe_file(path), source=path)


def recipe_changes(
    env: dict[str, Any] | None = None, ppo: dict[str, Any] | None = None, agents: int | None = None, **options: Any
) -> dict[str, Any]:
    """The partial recipe (for :meth:`Recipe.with_changes`) that options of ``sb3-formation train`` describe.

    :param env: :class:`FormationConfig` fields (``--env``)
    :param ppo: ``PPO`` keyword arguments
    :param agents: teams of this many agents (``--agents``): the task's ``n_agents``, and no ``team_sizes``
    :param options: options of :data:`RECIPE_OPTIONS` (``None`` values are left out). A ``minutes`` budget without a
        ``steps`` one replaces the recipe's steps budget, so that the time is the budget; ``recurrent=False`` without
        a ``cell`` drops the recipe's cell
    :raises ValueError: an option that is not a recipe's
    """
    unknown = sorted(set(options) - set(RECIPE_OPTIONS))
    if unknown:
        raise ValueError(f"unknown recipe option(s) {unknown}; valid: {list(RECIPE_OPTIONS)}")
    options = {name: value for name, value in options.items() if value is not None}
    if "minutes" in options and "steps" not in options:
        options["steps"] = None
    if options.get("recurrent") is False and "cell" not in options:
        options["cell"] = None  # an MLP has no cell
    changes: dict[str, Any] = {}
    for name, value in options.items():
        section, key = RECIPE_OPTIONS[name]
        if section is None:
            changes[key] = value
        else:
            changes.setdefault(section, {})[key] = value
    for section, values in (("env", env), ("ppo", ppo)):
        if values:
            changes[section] = {**changes.get(section, {}), **values}
    if agents is not None:
        changes.setdefault("env", {})["n_agents"] = agents
        changes.setdefault("team_sizes", None)
    return changes


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
