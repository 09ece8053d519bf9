"""The sections of a recipe (:class:`~sb3_formation.experiment.recipes.Recipe`) and of its ``run:`` options: one frozen
dataclass each, validated when made, read from its YAML mapping and written back.

Every class documents its fields in ``:param:`` lines, with units. A field made with :func:`option` is also an option of
``sb3-formation train`` and of :func:`~sb3_formation.experiment.recipes.layered_settings`: the option is declared once,
on its field, and the command line's flag takes its help from the field's ``:param:`` line (as CleanRL's and tyro's
dataclass arguments do).

The sections whose fields are keyword arguments of another class (``policy:`` the policy class's, ``ppo:`` SB3's
``PPO``'s, ``evaluation:`` :func:`~sb3_formation.experiment.evaluation.evaluate`'s) leave a field unset (``None``) to
that class's default and write only what they set, as RL Zoo keeps a run's hyperparameters: a recipe never pins a
default it did not choose.
"""

from __future__ import annotations

import dataclasses
import inspect
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, TypeVar

import torch
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import LinearSchedule

from sb3_formation.controllers.residual import check_residual_scale
from sb3_formation.env.config import TASKS, FormationConfig
from sb3_formation.env.disturbances import Disturbances, load_disturbances
from sb3_formation.env.scenes import SCENES
from sb3_formation.safety.filter import SafetyGains
from sb3_formation.safety.qp import check_solver
from sb3_formation.sb3.imitation import ImitationSettings
from sb3_formation.sb3.recurrent import CELLS, MAX_MESSAGE_SIZE
from sb3_formation.utils.checks import check_path, is_count, is_integer, is_number

#: Largest seed: numpy's and PyTorch's generators take seeds in [0, 2**32 - 1].
MAX_SEED = 2**32 - 1
#: The metadata key of a field that is an option of ``sb3-formation train`` (:func:`option`).
OPTION = "option"

SectionT = TypeVar("SectionT", bound="Section")


def option(
    default: Any = MISSING,
    *,
    default_factory: Any = MISSING,
    name: str | None = None,
    flag: str | None = None,
    choices: tuple[str, ...] | None = None,
) -> Any:
    """A dataclass field that is also an option of ``sb3-formation train``, with the field's ``:param:`` line as its help.

    :param default: the field's default (none: a required field)
    :param default_factory: makes the field's default instead
    :param name: the option's name, if not the field's (its keyword of ``layered_settings`` and its ``args`` attribute)
    :param flag: its command-line flag, if not ``--<name>`` with dashes
    :param choices: the values the command line accepts, if only some
    """
    metadata = {OPTION: {"name": name, "flag": flag, "choices": choices}}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=metadata)
    return field(default=default, metadata=metadata)


def field_docs(cls: type) -> dict[str, str]:
    """The text of each ``:param <name>:`` line of a class's docstring, its continuation lines joined."""
    docs: dict[str, str] = {}
    current = None
    for line in (inspect.getdoc(cls) or "").splitlines():
        match = re.match(r":param (\w+): ?(.*)", line)
        if match:
            current = match[1]
            docs[current] = match[2]
        elif current is not None and line.startswith(" ") and line.strip():
            docs[current] += " " + line.strip()
        else:
            current = None
    return docs


def plain(value: Any) -> Any:
    """Tuples to lists, recursively, so that YAML writes plain lists."""
    if isinstance(value, dict):
        return {key: plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    return value


def _names(names: list[str]) -> str:
    """``a, b and c``."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def keys_error(where: str, required: list[str], optional: list[str], unknown: list[str], missing: list[str]) -> ValueError:
    """The one-line error of a mapping with unknown or missing keys, naming the keys it takes.

    :param where: the mapping (a section's key, a recipe)
    :param required: the keys it needs
    :param optional: the keys it may give
    :param unknown: the keys given that it does not take
    :param missing: the keys it needs that are not given
    """
    takes = [f"needs {_names(required)}"] if required else []
    takes += [f"may give {', '.join(optional)}"] if optional else []
    problems = ", ".join(f"{kind} keys {keys}" for kind, keys in (("unknown", unknown), ("missing", missing)) if keys)
    return ValueError(f"{where} {' and '.join(takes)}: {problems}")


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


def _is_schedule(value: Any) -> bool:
    try:
        schedule(value)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class Section:
    """Base of the sections: a frozen dataclass validated in ``__post_init__`` (:meth:`_check` names the section, the
    field and what it may be), read from its YAML mapping by :meth:`from_dict` and written back by :meth:`to_dict`."""

    #: the section's key in a recipe file
    key: ClassVar[str] = ""
    #: the field that holds the keys of the mapping that are not fields (written flat beside them), if any
    rest: ClassVar[str | None] = None
    #: write only the fields that are set (not None): the fields are keyword arguments of another class
    sparse: ClassVar[bool] = False

    @classmethod
    def from_dict(cls: type[SectionT], values: Any) -> SectionT:
        """The section of a recipe file's mapping; unknown and missing keys are errors that name the keys it takes."""
        if not isinstance(values, dict):
            raise ValueError(f"{cls.key} must be a mapping, got {values!r}")
        names = [item.name for item in fields(cls) if item.name != cls.rest]
        required = [item.name for item in fields(cls) if item.default is MISSING and item.default_factory is MISSING]
        others = {key: value for key, value in values.items() if key not in names}
        missing = [name for name in required if name not in values]
        if missing or (others and cls.rest is None):
            unknown = [] if cls.rest is not None else sorted(others, key=str)
            raise keys_error(cls.key, required, [name for name in names if name not in required], unknown, missing)
        given = {key: value for key, value in values.items() if key in names}
        return cls(**given, **({} if cls.rest is None else {cls.rest: others}))

    def to_dict(self) -> dict[str, Any]:
        """The section as plain YAML data, as :meth:`from_dict` reads it."""
        values: dict[str, Any] = {}
        for item in fields(self):
            value = getattr(self, item.name)
            if item.name == self.rest:
                values.update(value)
            elif not (self.sparse and value is None):
                values[item.name] = value
        return plain(values)

    def replace(self: SectionT, **changes: Any) -> SectionT:
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)

    def _check(self, name: str, allowed: str, valid: Callable[[Any], bool]) -> None:
        """Raise ``ValueError("<section>: <name> must be <allowed>, got <value>")`` unless ``valid(value)``."""
        value = getattr(self, name)
        if not valid(value):
            raise ValueError(f"{self.key}: {name} must be {allowed}, got {value!r}")


def _optional(valid: Callable[[Any], bool]) -> Callable[[Any], bool]:
    """``valid``, or unset (``None``)."""
    return lambda value: value is None or valid(value)


def _is_bool(value: Any) -> bool:
    return isinstance(value, bool)


def _at_least(low: int) -> Callable[[Any], bool]:
    """An integer >= ``low``."""
    return lambda value: is_integer(value) and value >= low


@dataclass(frozen=True)
class EnvSection(Section):
    """``env:``: the task, a name of :data:`~sb3_formation.env.config.TASKS`, and the fields that change it.

    :param task: a name of :data:`~sb3_formation.env.config.TASKS` (the thesis's tables 4.1 and 5.1)
    :param overrides: :class:`~sb3_formation.env.config.FormationConfig` fields replacing the task's values (written
        beside ``task:`` in a recipe file; on the command line FIELD=VALUE, the value read as YAML, repeatable);
        ``scenes`` must be a name of :data:`sb3_formation.env.scenes.SCENES`
    """

    key: ClassVar[str] = "env"
    rest: ClassVar[str | None] = "overrides"

    task: str
    overrides: Mapping[str, Any] = option(default_factory=dict, name="env")

    def __post_init__(self) -> None:
        self._check("task", f"one of {sorted(TASKS)}", lambda value: isinstance(value, str) and value in TASKS)
        self._check("overrides", "a mapping of FormationConfig fields", lambda value: isinstance(value, Mapping))
        object.__setattr__(self, "overrides", dict(self.overrides))
        scenes = self.config().scenes  # the task validates the fields
        if scenes not in SCENES:
            raise ValueError(
                f"env: scenes must be a name of sb3_formation.env.scenes.SCENES ({', '.join(SCENES)}), got {scenes!r}"
            )

    def config(self, **changes: Any) -> FormationConfig:
        """The task's configuration with the overrides, then ``changes`` (:class:`FormationConfig` fields), applied."""
        return FormationConfig.task(self.task, **{**self.overrides, **changes})


@dataclass(frozen=True)
class PolicySection(Section):
    """``policy:``: the network, and keyword arguments of the policy class (unset: the class's default).

    :param recurrent: a recurrent actor and critic (figs 5.1, 5.2:
        :class:`~sb3_formation.sb3.recurrent.RecurrentFormationPolicy`), else an MLP
        (:class:`~sb3_formation.sb3.policies.FormationPolicy`)
    :param cell: the recurrent cell, gru or lstm (recurrent policies only; unset: gru)
    :param team_critic: the critic reads the whole team (fig. 4.3); unset: exactly when the task uses the team reward
    :param sigma: the actions' standard deviation (in units of the action bound, fixed unless learned; thesis 4.3: 0.7)
    :param learn_sigma: learn a state-independent log-std starting at log(sigma)
    :param action_scale: factor on the tanh of the actor's output (thesis 4.1.2: 0.01 for the chapter-4 individual scheme)
    :param net_arch: layer widths: a list for both networks, or widths by part, ``{pi: [...], vf: [...]}`` (a recurrent
        policy's parts also ``pi_recurrent``, ``pi_after``, ``vf_recurrent``, ``vf_after``)
    :param message_size: recurrent policies only: values of the message each agent sends its ring neighbours every
        step, received one step late (unset: 0, none)
    :param memory: recurrent policies only: carry the recurrent state from step to step (unset: true; false: an
        ablation that acts on the current observation and messages only)
    """

    key: ClassVar[str] = "policy"
    sparse: ClassVar[bool] = True
    #: the fields that choose the network rather than being passed to it
    CHOICES: ClassVar[tuple[str, ...]] = ("recurrent", "cell", "team_critic")

    recurrent: bool = option(False)
    cell: str | None = option(None, choices=CELLS)
    team_critic: bool | None = None
    sigma: float | None = None
    learn_sigma: bool | None = None
    action_scale: float | None = None
    net_arch: list[int] | dict[str, list[int] | int] | None = None
    message_size: int | None = None
    memory: bool | None = None

    def __post_init__(self) -> None:
        self._check("recurrent", "true or false", _is_bool)
        self._check("cell", f"one of {CELLS} or null", _optional(lambda value: value in CELLS))
        self._check("team_critic", "true, false or null (null: with the team reward)", _optional(_is_bool))
        for name in ("sigma", "action_scale"):
            self._check(name, "a finite number > 0", _optional(lambda value: is_number(value) and value > 0))
        self._check("learn_sigma", "true or false", _optional(_is_bool))
        self._check("net_arch", "a list of layer widths or a mapping of parts to widths", _optional(_is_net_arch))
        self._check(
            "message_size",
            f"an integer in [0, {MAX_MESSAGE_SIZE}]",
            _optional(lambda value: is_integer(value) and 0 <= value <= MAX_MESSAGE_SIZE),
        )
        self._check("memory", "true or false", _optional(_is_bool))
        for name in ("cell", "message_size", "memory"):
            if getattr(self, name) is not None and not self.recurrent:
                raise ValueError(f"policy: {name} {getattr(self, name)!r} applies to recurrent policies only")
        if self.recurrent and self.team_critic:
            raise ValueError("policy: the team critic has no recurrent version: set recurrent: false or team_critic: false")

    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of the policy class that the section sets (the cell and the team's size apart)."""
        return {name: value for name, value in self.to_dict().items() if name not in self.CHOICES}


def _is_widths(value: Any) -> bool:
    return isinstance(value, (list, tuple)) and all(is_integer(width) and width >= 1 for width in value)


def _is_net_arch(value: Any) -> bool:
    """A list of layer widths, or a mapping of parts to such lists or to one width (a recurrent layer's)."""
    if isinstance(value, dict):
        return all(_is_widths(widths) or _at_least(1)(widths) for widths in value.values())
    return _is_widths(value)


@dataclass(frozen=True)
class PPOSection(Section):
    """``ppo:``: keyword arguments of SB3's ``PPO`` (of :class:`~sb3_formation.sb3.recurrent.RecurrentFormationPPO` for a
    recurrent policy), as RL Zoo's hyperparameter files give them; unset: SB3's default.

    :param learning_rate: Adam's step size, a number or ``{start: a, end: b}`` (linear from a to b over the budget)
    :param n_steps: steps each slot plays per iteration (the rollout; thesis 4.3: 128, the soft horizon H_s)
    :param batch_size: agent-steps per mini-batch (>= 2: advantages are normalised over each)
    :param n_epochs: passes over the rollout per iteration
    :param gamma: discount factor per step, in (0, 1]
    :param gae_lambda: GAE's lambda, in [0, 1]
    :param clip_range: PPO's clip epsilon_p, a number or ``{start: a, end: b}``
    :param clip_range_vf: the value clip epsilon_v (in units of the return), or null for none (SB3's default)
    :param normalize_advantage: normalise the advantages over each mini-batch
    :param ent_coef: weight of the entropy bonus in the loss
    :param vf_coef: weight of the value loss in the loss
    :param max_grad_norm: the gradients' norm is clipped to this
    :param target_kl: stop an iteration's epochs once the KL divergence passes 1.5 x this, or null for no stop (SB3's
        default)
    :param stats_window_size: episodes in the rolling means of SB3's rollout/ logs
    :param max_sequence_length: recurrent policies only: longest sequence replayed in an update (steps)
    """

    key: ClassVar[str] = "ppo"
    sparse: ClassVar[bool] = True
    #: Fields whose null means "off" (no value clip, no KL stop), which is SB3's default: written either way, so that a
    #: run's record says whether they were on.
    WRITTEN: ClassVar[tuple[str, ...]] = ("clip_range_vf", "target_kl")

    learning_rate: float | dict[str, float] | None = None
    n_steps: int | None = None
    batch_size: int | None = None
    n_epochs: int | None = None
    gamma: float | None = None
    gae_lambda: float | None = None
    clip_range: float | dict[str, float] | None = None
    clip_range_vf: float | dict[str, float] | None = None
    normalize_advantage: bool | None = None
    ent_coef: float | None = None
    vf_coef: float | None = None
    max_grad_norm: float | None = None
    target_kl: float | None = None
    stats_window_size: int | None = None
    max_sequence_length: int | None = None

    @classmethod
    def from_dict(cls, values: Any) -> PPOSection:
        if isinstance(values, dict) and "policy_kwargs" in values:
            raise ValueError("ppo: policy_kwargs is not a ppo setting: policy keyword arguments go under policy:")
        return super().from_dict(values)

    def __post_init__(self) -> None:
        for name in ("learning_rate", "clip_range", "clip_range_vf"):
            self._check(name, "a number > 0 or {start: a, end: b} with numbers > 0", _optional(_is_schedule))
        for name in ("n_steps", "n_epochs", "stats_window_size", "max_sequence_length"):
            self._check(name, "an integer >= 1", _optional(_at_least(1)))
        # SB3 normalises the advantages over each mini-batch: one sample has no spread
        self._check("batch_size", "an integer >= 2 (advantages are normalised over a mini-batch)", _optional(_at_least(2)))
        self._check("gamma", "a number in (0, 1]", _optional(lambda value: is_number(value) and 0 < value <= 1))
        self._check("gae_lambda", "a number in [0, 1]", _optional(lambda value: is_number(value) and 0 <= value <= 1))
        for name in ("ent_coef", "vf_coef"):
            self._check(name, "a finite number >= 0", _optional(lambda value: is_number(value) and value >= 0))
        for name in ("max_grad_norm", "target_kl"):
            self._check(name, "a finite number > 0", _optional(lambda value: is_number(value) and value > 0))
        self._check("normalize_advantage", "true or false", _optional(_is_bool))

    def to_dict(self) -> dict[str, Any]:
        """The settings the section gives, and :attr:`WRITTEN` whether given or not."""
        return {**super().to_dict(), **{name: getattr(self, name) for name in self.WRITTEN if getattr(self, name) is None}}


@dataclass(frozen=True)
class CurriculumSection(Section):
    """``curriculum:``: the three stages of thesis 4.3 and 5.3.

    :param iterations: PPO iterations of stages 1, 2 and 3 (with a budget in training:, their proportions)
    :param success_threshold: end stages 1-2 early once the rolling success rate reaches this, in [0, 1]
        (null: after their iterations only, as the thesis)
    """

    key: ClassVar[str] = "curriculum"

    iterations: tuple[int, int, int] = option()
    success_threshold: float | None = option(None)

    def __post_init__(self) -> None:
        self._check(
            "iterations",
            "three integers >= 0, not all 0",
            lambda value: (
                isinstance(value, (list, tuple)) and len(value) == 3 and all(map(is_count, value)) and sum(value) > 0
            ),
        )
        object.__setattr__(self, "iterations", tuple(int(count) for count in self.iterations))
        self._check(
            "success_threshold", "a number in [0, 1] or null", _optional(lambda value: is_number(value) and 0 <= value <= 1)
        )


#: The most episodes an evaluation records step by step (``record``): they are held in memory until written, about
#: 6 MB each at the scene families' 2,500 steps and 6 agents, so 0.6 GB at most.
MAX_RECORDED_EPISODES = 100


def check_record(record: Any, where: str = "") -> None:
    """Refuse to record more episodes step by step than :data:`MAX_RECORDED_EPISODES` (or fewer than none).

    :param record: the episodes to record
    :param where: what the message begins with (e.g. the section's key)
    :raises ValueError: naming the option (``--trajectories``) and why there is a limit
    """
    if not (is_count(record) and record <= MAX_RECORDED_EPISODES):
        raise ValueError(
            f"{where}record (--trajectories) must be in [0, {MAX_RECORDED_EPISODES}], got {record}: recorded episodes are "
            "held in memory until written (about 6 MB for a 2,500-step episode of 6 agents)"
        )


@dataclass(frozen=True)
class EvaluationSection(Section):
    """``evaluation:``: the protocol that measures a trained policy, keyword arguments of
    :func:`~sb3_formation.experiment.evaluation.evaluate` (unset: its default).

    :param episodes: episodes played (thesis 4.4: 500, 5.4: 200)
    :param stage: curriculum stage of the episodes, 1 to 3 (the thesis's: 3)
    :param seed: episode k plays the scenario of seed + k
    :param n_envs: teams played at once
    :param deterministic: play the policy's mean action (else sample it)
    :param record: episodes whose steps are recorded for the figures (at most :data:`MAX_RECORDED_EPISODES`)
    """

    key: ClassVar[str] = "evaluation"
    sparse: ClassVar[bool] = True

    episodes: int
    stage: int | None = None
    seed: int | None = None
    n_envs: int | None = None
    deterministic: bool | None = None
    record: int | None = None

    def __post_init__(self) -> None:
        self._check("episodes", "an integer >= 1", _at_least(1))
        self._check("stage", "1, 2 or 3", _optional(lambda value: is_integer(value) and 1 <= value <= 3))
        self._check("seed", "an integer in [0, 2**32 - 1]", _optional(lambda value: is_count(value) and value <= MAX_SEED))
        self._check("n_envs", "an integer >= 1", _optional(_at_least(1)))
        self._check("deterministic", "true or false", _optional(_is_bool))
        if self.record is not None:
            check_record(self.record, f"{self.key}: ")

    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :func:`~sb3_formation.experiment.evaluation.evaluate` that the protocol sets (each
        field is one, of the same name)."""
        return self.to_dict()


@dataclass(frozen=True)
class TrainingSection(Section):
    """``training:``: training features beyond the thesis (its own: none of them) and the budget.

    :param normalize_reward: divide the rewards by a running std of the discounted return (SB3's VecNormalize)
    :param center_observations: subtract the observations' running mean too (thesis 3.1.4 only scales them)
    :param steps: budget in agent-steps: the curriculum's iterations become proportions of it
    :param minutes: budget in minutes of training wall-clock (given alone, it replaces a recipe's steps budget)
    :param eval_every: evaluate every this many iterations and keep the best model (best_model.zip)
    :param eval_episodes: episodes of each of those evaluations
    """

    key: ClassVar[str] = "training"

    normalize_reward: bool = option(False)
    center_observations: bool = False
    steps: int | None = option(None)
    minutes: float | None = option(None)
    eval_every: int | None = option(None)
    eval_episodes: int = 20

    def __post_init__(self) -> None:
        for name in ("normalize_reward", "center_observations"):
            self._check(name, "true or false", _is_bool)
        for name in ("steps", "eval_every"):
            self._check(name, "an integer >= 1 or null", _optional(_at_least(1)))
        self._check("eval_episodes", "an integer >= 1", _at_least(1))
        self._check("minutes", "a finite number > 0 or null", _optional(lambda value: is_number(value) and value > 0))


def _is_mapping(value: Any) -> bool:
    return isinstance(value, dict)


@dataclass(frozen=True)
class ResidualSection(Section):
    """``residual:``: train a bounded correction of a controller; the env receives
    ``clip(a_controller + scale * a_policy, -1, 1)``.

    :param controller: a name of :data:`~sb3_formation.controllers.CONTROLLERS` (a decentralised one)
    :param scale: bound of the correction, a fraction of F_max in (0, 2]
    :param gains: the controller's keyword arguments (unset: its documented defaults)
    """

    key: ClassVar[str] = "residual"

    controller: str
    scale: float
    gains: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._check("controller", "a controller's name", lambda value: isinstance(value, str))
        self._check("gains", "a mapping of gain names to values", _is_mapping)
        try:
            check_residual_scale(self.scale)
        except ValueError as error:
            raise ValueError(f"residual: {error}") from None


@dataclass(frozen=True)
class ImitationSection(Section):
    """``imitation:``: pretrain the actor on a controller's actions before PPO (behaviour cloning with DAgger relabelling).

    :param controller: the teacher, a name of :data:`~sb3_formation.controllers.CONTROLLERS`
    :param gains: the teacher's keyword arguments (unset: its documented defaults)
    :param settings: fields of :class:`~sb3_formation.sb3.imitation.ImitationSettings` (rounds, steps, epochs,
        batch_size, learning_rate, critic_warmup), written beside ``controller:``
    """

    key: ClassVar[str] = "imitation"
    rest: ClassVar[str | None] = "settings"

    controller: str
    gains: dict[str, Any] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._check("controller", "a controller's name", lambda value: isinstance(value, str))
        self._check("gains", "a mapping of gain names to values", _is_mapping)
        names = [item.name for item in fields(ImitationSettings)]
        unknown = sorted(set(self.settings) - set(names), key=str)
        if unknown:
            raise keys_error(self.key, ["controller"], ["gains", *names], unknown, [])
        self.imitation_settings()

    def imitation_settings(self) -> ImitationSettings:
        """How the actor is pretrained."""
        return ImitationSettings(**self.settings)


@dataclass(frozen=True)
class SafetySection(Section):
    """``safety:``: train behind the safety filter ("shielded" PPO, ``docs/safety.md``); the env applies the filtered
    action, PPO keeps its own. The trained policy acts behind the same filter wherever it is loaded or exported.

    :param penalty: reward lost per unit of the filter's change ``|a_safe - a|`` of each agent's action (>= 0)
    :param gains: fields of :class:`~sb3_formation.safety.filter.SafetyGains` (unset: its defaults), written beside
        ``penalty:`` (:func:`~sb3_formation.experiment.recipes.read_safety_gains` reads them)
    """

    key: ClassVar[str] = "safety"
    rest: ClassVar[str | None] = "gains"

    penalty: float = 0.0
    gains: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._check("penalty", "a finite number >= 0", lambda value: is_number(value) and value >= 0)
        try:
            check_solver(SafetyGains.from_dict(self.gains).solver)
        except ValueError as error:
            raise ValueError(f"safety: {error}") from None


@dataclass(frozen=True)
class DisturbancesSection(Section):
    """``disturbances:``: train under randomised disturbances (domain randomisation, ``docs/disturbances.md``): each
    training episode draws its level uniformly between the ideal world and these. Evaluation stays ideal unless asked.
    A talking policy's messages arrive intact in training (its update replays them through whole teams' sequences);
    the ``communication`` part acts in evaluation.

    :param profile: train under randomised disturbances up to a profile (realistic, harsh) or a disturbances file:
        each episode draws its level between ideal and it
    :param overrides: parts of the disturbances replacing the profile's, written beside ``profile:`` as in a
        disturbances file (e.g. ``timing: {action_delay: [0, 1]}``)
    """

    key: ClassVar[str] = "disturbances"
    rest: ClassVar[str | None] = "overrides"

    profile: str = option(name="disturbances")
    overrides: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._check("profile", "a profile's name or a disturbances file", lambda value: isinstance(value, str))
        try:
            self.disturbances()
        except (ValueError, FileNotFoundError) as error:
            raise ValueError(f"disturbances: {error}") from None

    def disturbances(self) -> Disturbances:
        """The disturbances training draws its levels up to, randomised."""
        return Disturbances.from_dict(self.overrides, load_disturbances(self.profile)).randomised()


#: The sections of a recipe by their keys, in the order a recipe file writes them.
SECTIONS: dict[str, type[Section]] = {
    section.key: section
    for section in (
        EnvSection,
        PolicySection,
        PPOSection,
        CurriculumSection,
        EvaluationSection,
        TrainingSection,
        ResidualSection,
        ImitationSection,
        SafetySection,
        DisturbancesSection,
    )
}


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


def _is_seed(value: Any) -> bool:
    return is_count(value) and value <= MAX_SEED


@dataclass(frozen=True)
class RunOptions(Section):
    """``run:``: how one run of a recipe is carried out; none of it changes what the recipe means.

    :param seed: seed of PPO and of the teams' scenario generators, in [0, 2**32 - 1]
    :param seeds: the seeds of ``sb3-formation sweep`` (one run each; ``train`` uses seed)
    :param device: torch device for PPO: auto, cpu, cuda or cuda:<index>
    :param workers: processes stepping the teams, this one included (at most n_envs)
    :param logdir: folder in which run folders are made
    :param checkpoint_every: iterations between checkpoints
    :param progress_bar: show a progress bar
    :param evaluate: after training, evaluate the final model on the recipe's evaluation protocol into eval/
    """

    key: ClassVar[str] = "run"

    seed: int = option(0)
    seeds: tuple[int, ...] | None = None
    device: str = option("auto")
    workers: int = option(1)
    logdir: str = option("runs")
    checkpoint_every: int = option(50)
    progress_bar: bool = option(True, flag="--progress")
    evaluate: bool = option(False)

    def __post_init__(self) -> None:
        self._check("seed", "an integer in [0, 2**32 - 1]", _is_seed)
        self._check(
            "seeds", "a non-empty list of integers", _optional(lambda value: isinstance(value, (list, tuple)) and bool(value))
        )
        for seed in self.seeds or ():
            if not _is_seed(seed):
                raise ValueError(f"run: each of seeds must be an integer in [0, 2**32 - 1], got {seed!r}")
        object.__setattr__(self, "seeds", None if self.seeds is None else tuple(int(seed) for seed in self.seeds))
        check_device(self.device)
        for name in ("workers", "checkpoint_every"):
            self._check(name, "an integer >= 1", _at_least(1))
        self._check("logdir", "a folder name", lambda value: isinstance(value, (str, os.PathLike)))
        check_path(self.logdir, "logdir")
        object.__setattr__(self, "logdir", os.fspath(self.logdir))
        for name in ("progress_bar", "evaluate"):
            self._check(name, "true or false", _is_bool)
