"""The policy seam: anything that acts in the formation env, learned or hand-written.

A :class:`TeamPolicy` has Stable-Baselines3's ``predict(observation, state, episode_start, deterministic)`` over the
*raw* observations of whole teams: row k is agent ``k % n`` of team ``k // n`` (the slot order of
:class:`~sb3_formation.sb3.vec_env.FormationVecEnv`), each row the env's own observation (thesis Table 3.1, SI
units). Whatever a policy needs beyond that (normalisation, team observations for a critic, an agent index) it does
itself: evaluation, rendering and comparison never need to know what kind of policy they drive. A policy that draws
random numbers of its own (not torch's global generator) may also have ``seed(seed)``: evaluation calls it with its
seed, so that the same seed gives the same episodes.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import fields
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.state import TeamState
from sb3_formation.utils.checks import is_number

GainsT = TypeVar("GainsT")


@runtime_checkable
class TeamPolicy(Protocol):
    """Anything that acts: SB3's ``predict`` over raw team observations, the config it acts in, and :meth:`fit`."""

    #: The task the policy acts in by default (for a trained policy: the one it was trained in).
    config: FormationConfig

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        """Actions ``(k, 2)`` for ``(k, obs_dim)`` raw observations of whole teams, and the policy's next state.

        :param observation: raw observations; row k is agent ``k % n`` of team ``k // n``
        :param state: what the previous call returned (``None`` at the start)
        :param episode_start: ``(k,)`` flags: these rows start a new episode (reset their memory)
        :param deterministic: act without exploration noise
        """
        ...

    def fit(self, config: FormationConfig) -> TeamPolicy:
        """A policy acting in envs of ``config`` (``self`` if it already does).

        :raises ValueError: the policy cannot act there (the message names every difference)
        """
        ...


@runtime_checkable
class PrivilegedPolicy(TeamPolicy, Protocol):
    """A policy that also reads the map: the episode loop gives it each team's state when the team's episode starts.
    Not decentralised (an agent's sensors see less), hence labelled ``privileged``."""

    privileged: bool

    def start_episodes(self, teams: Sequence[int], states: Sequence[TeamState]) -> None:
        """Take the states after the reset of ``teams`` (team k holds rows k n to (k + 1) n - 1 of ``predict``)."""
        ...


def check_gains(gains: Any) -> None:
    """Refuse a gains dataclass any of whose values is not a finite number >= 0 (a bool where its default is one).

    :raises ValueError: naming the gain and what it must be
    """
    for item in fields(gains):
        value = getattr(gains, item.name)
        if isinstance(item.default, bool):
            valid, allowed = isinstance(value, bool), "true or false"
        else:
            valid, allowed = is_number(value) and value >= 0, "a finite number >= 0"
        if not valid:
            raise ValueError(f"{type(gains).__name__}.{item.name}={value!r} is invalid: it must be {allowed}")


class Controller(ABC):
    """Base class of hand-written controllers: each agent acts from its own raw observation and its index.

    Controllers are decentralised: :meth:`act` sees one row per agent (the fields of :attr:`layout`) and the agents'
    indices in their teams, never the world. Subclasses take their gains as keyword arguments of ``__init__`` and store
    them in :attr:`gains` (evaluation summaries record them). The one exception is labelled: a controller whose
    ``privileged`` is true also reads each team's map when its episode starts (:class:`PrivilegedPolicy`).

    A controller may keep a memory of each agent's past observations (e.g.
    :class:`~sb3_formation.controllers.shrinking.ShrinkingController`, one row of memory per observation row). The
    memory is not an attribute: it is SB3's ``state`` of :meth:`predict` and :meth:`agent_step`, which the caller
    hands back with the next rows and which ``episode_start`` (or ``None`` as the state) resets; a memoryless
    controller's state is ``None``. So one controller serves any number of teams and episodes at once, and whoever
    drives it carries its memory: the episode loop of evaluation, and
    :class:`~sb3_formation.controllers.residual.ResidualAdapter` for a residual policy (in evaluation, training and the
    ONNX runtime).

    :param config: the task configuration the controller acts in
    """

    def __init__(self, config: FormationConfig) -> None:
        self.config = config
        #: observation field name -> slice of a row
        self.layout: dict[str, slice] = observation_layout(observation_fields(config))
        self.gains: dict[str, Any] = {}

    def _take_gains(self, kind: type[GainsT], gains: dict[str, Any]) -> GainsT:
        """The gains dataclass ``kind`` built from keyword values, recorded in :attr:`gains`.

        :raises ValueError: a name that is not one of ``kind``'s fields (the valid ones are listed)
        """
        names = [item.name for item in fields(kind)]  # type: ignore[arg-type]  # kind is a dataclass
        unknown = sorted(set(gains) - set(names))
        if unknown:
            raise ValueError(f"unknown gains {unknown} of {type(self).__name__}; gains: {names}")
        settings = kind(**gains)
        self.gains = {name: getattr(settings, name) for name in names}
        return settings

    def fit(self, config: FormationConfig) -> Controller:
        """The same controller (a shallow copy: same gains, same generator) acting in envs of ``config``; the copy's
        :meth:`_fit_task` derives what depends on the task."""
        if config == self.config:
            return self
        fitted = copy.copy(self)
        fitted.config = config
        fitted.layout = observation_layout(observation_fields(config))
        fitted._fit_task()
        return fitted

    def _fit_task(self) -> None:
        """Derive what the controller keeps of its task (called by subclasses' ``__init__`` and by :meth:`fit`); a
        controller that keeps nothing of it leaves this as it is."""
        return

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        """SB3's signature: :meth:`agent_step` on every row (row k: agent k % n), actions clipped to [-1, 1]."""
        observation = np.asarray(observation, dtype=np.float64)
        rows = observation.reshape(-1, observation.shape[-1])
        agents = np.arange(len(rows)) % self.config.n_agents
        actions, state = self.agent_step(rows, agents, state, episode_start, deterministic)
        return actions.reshape(*observation.shape[:-1], 2), state

    def agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        """Actions ``(k, 2)`` (as :meth:`agent_actions`) for rows of any agents, and the controller's next state (its
        memory of these rows): what every caller that carries a controller's memory calls (:meth:`predict`, and
        :class:`~sb3_formation.controllers.residual.ResidualAdapter`). A memoryless controller returns ``None``; one with
        memory overrides this.

        :param observations: ``(k, obs_dim)`` raw observations
        :param agents: ``(k,)`` each row's agent index in its team
        :param state: what the previous call returned for these rows (``None`` at the start)
        :param episode_start: ``(k,)`` flags: these rows start an episode (their memory is reset)
        :param deterministic: act without noise
        """
        return self.agent_actions(observations, agents, deterministic), None

    def agent_actions(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """:meth:`act` on rows of any agents (e.g. one robot's), clipped to [-1, 1], as float32 ``(k, 2)``.

        :param observations: ``(k, obs_dim)`` raw observations
        :param agents: ``(k,)`` each row's agent index in its team
        :param deterministic: act without noise
        """
        observations = np.asarray(observations, dtype=np.float64)
        return np.clip(self.act(observations, np.asarray(agents), deterministic), -1.0, 1.0).astype(np.float32)

    @abstractmethod
    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        """Actions ``(k, 2)`` in [-1, 1] (fractions of F_max) for ``(k, obs_dim)`` raw observations.

        :param observations: one row per agent, fields as in :attr:`layout`
        :param agents: ``(k,)`` each row's agent index in its team (0 to n - 1)
        :param deterministic: act without noise (for controllers that have any)
        """
