"""The policy seam: anything that acts in the formation env, learned or hand-written, answers the same two calls.

- **One per team**, Stable-Baselines3's ``predict(observation, state, episode_start, deterministic) -> (actions,
  state)`` over the *raw* observations of whole teams: row k is agent ``k % n`` of team ``k // n`` (the slot order of
  :class:`~sb3_formation.sb3.vec_env.FormationVecEnv`), each row the env's own observation (thesis Table 3.1, SI
  units). Evaluation, rendering and comparison call it; where agents may fail it also takes ``flying``, the rows
  whose agents still fly.
- **One per agent**, ``agent_step(observations, agents, state, episode_start, received, deterministic) ->``
  :class:`AgentStep` ``(action, state, message)``, for rows of any agents (e.g. the one a robot hosts) with their
  places on their rings (:func:`ring_places`) and the messages their ring neighbours sent them. The robot's on-board
  pipeline calls it.

:class:`Policy` writes ``predict`` once over ``agent_step``: it routes the messages that a talking policy's agents
send (``message_size`` M > 0) to their ring neighbours in the rows' teams, one step late, and its state is then the pair
(the agents' state, the messages they sent). Every kind of policy (controllers, residual policies, trained SB3 models,
exported ONNX files, a policy behind the safety filter) is a :class:`Policy`. Whatever a policy needs beyond the raw
rows (normalisation, an agent index) it does itself. A policy that draws random numbers of its own (not torch's global
generator) may also have ``seed(seed)``: evaluation calls it with its seed, so that the same seed gives the same
episodes. Whether a policy can act in a task is decided by one check, :func:`check_fit`.
"""

from __future__ import annotations

import copy
import functools
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import fields
from typing import Any, NamedTuple, Protocol, TypeVar, runtime_checkable

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbed import MessageChannel
from sb3_formation.env.geometry import flying_rows, reference_bearings, reference_polygon, ring_rows
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.state import TeamState
from sb3_formation.utils.checks import is_number

GainsT = TypeVar("GainsT")

#: The task settings that shape an agent's observation (its fields and their sizes) or what an action means.
OBSERVATION_SHAPING_FIELDS = ("n_agents", "dynamics", "lidar_rays", "observe_reference_bearings")


class AgentStep(NamedTuple):
    """What :meth:`Policy.agent_step` returns for ``k`` agents."""

    action: np.ndarray  #: ``(k, 2)`` float32 actions in [-1, 1]
    state: Any  #: the agents' next state (what the next call takes; ``None`` for a policy without memory)
    message: np.ndarray  #: ``(k, M)`` float32 messages the agents send their ring neighbours (``(k, 0)`` if none)


@runtime_checkable
class TeamPolicy(Protocol):
    """Anything that acts: the team call, the agent call, the config it acts in and :meth:`fit` (see the module
    docstring; :class:`Policy` implements it)."""

    @property
    def config(self) -> FormationConfig:
        """The task the policy acts in by default (for a trained policy: the one it was trained in)."""
        ...

    @property
    def message_size(self) -> int:
        """M, the values of the message each agent sends its ring neighbours every step (0: none)."""
        ...

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
        *,
        channel: MessageChannel | None = None,
        flying: np.ndarray | None = None,
    ) -> tuple[np.ndarray, Any]:
        """Actions ``(k, 2)`` for ``(k, obs_dim)`` raw observations of whole teams, and the policy's next state.

        :param observation: raw observations; row k is agent ``k % n`` of team ``k // n``
        :param state: what the previous call returned (``None`` at the start)
        :param episode_start: ``(k,)`` flags: these rows start a new episode (reset their memory)
        :param deterministic: act without exploration noise
        :param channel: the links that carry a talking policy's messages, when they lose or delay them (``None``:
            every message arrives one step late)
        :param flying: ``(k,)`` bool: the rows whose agents fly (``None``: every one); the others failed, and the
            flying agents of a team fly the ring of their number (:func:`~sb3_formation.env.geometry.flying_ring`)
        """
        ...

    def agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        received: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> AgentStep:
        """Actions, next state and sent messages of rows of any agents.

        :param observations: ``(k, obs_dim)`` raw observations
        :param agents: ``(k,)`` each row's agent index in its team, or ``(k, 2)`` its place on its ring and the ring's
            size (a team whose agents failed: :func:`ring_places`)
        :param state: what the previous call returned for these rows (``None`` at the start)
        :param episode_start: ``(k,)`` flags: these rows start an episode (their state is reset)
        :param received: ``(k, 2, M)`` (or ``(k, 2 M)``) what each row's preceding and succeeding neighbours sent at
            their last step (``None``: zeros, as at an episode's start); a talking policy's only
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


def check_fit(who: str, trained: FormationConfig, config: FormationConfig, any_team_size: bool = False) -> None:
    """Refuse a task whose agents observe or act otherwise than the policy's: the one fit check of every policy.

    :param who: the policy, for the message (e.g. its model file)
    :param trained: the task the policy acts in (for a learned one: the task it was trained in)
    :param config: the task it is asked to act in
    :param any_team_size: it acts in teams of any size (trained on several): ``n_agents`` may differ
    :raises ValueError: one line naming every setting of :data:`OBSERVATION_SHAPING_FIELDS` that differs (or the
        observation fields, if they differ otherwise)
    """
    differences = [
        f"{name}={getattr(trained, name)!r} in the model, {getattr(config, name)!r} in the env"
        for name in OBSERVATION_SHAPING_FIELDS
        if getattr(trained, name) != getattr(config, name) and not (name == "n_agents" and any_team_size)
    ]
    if not differences and _field_sizes(trained) != _field_sizes(config):
        differences = [f"observation fields {_field_sizes(trained)} in the model, {_field_sizes(config)} in the env"]
    if differences:
        raise ValueError(f"{who} does not fit this env: " + "; ".join(differences))


def _field_sizes(config: FormationConfig) -> list[tuple[str, int]]:
    return [(field.name, field.size) for field in observation_fields(config)]


class Policy(ABC):
    """Base of every policy: :meth:`agent_step` and :meth:`fit` are a subclass's; :meth:`predict` (the team call) is
    written here once over :meth:`agent_step`, routing a talking policy's messages within each team. A subclass sets
    :attr:`config`, the task the policy acts in.
    """

    config: FormationConfig

    @property
    def message_size(self) -> int:
        """M, the values of the message each agent sends its ring neighbours every step (0: none)."""
        return 0

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
        *,
        channel: MessageChannel | None = None,
        flying: np.ndarray | None = None,
    ) -> tuple[np.ndarray, Any]:
        """SB3's signature over raw observations of whole teams (row k: agent ``k % n`` of team ``k // n``):
        :meth:`agent_step` on every row. A talking policy's state is the pair (the agents' state, the ``(k, M)``
        messages they sent); each row receives, one step late, the messages of its ring neighbours in its team
        (zeros where an episode starts), or what ``channel`` delivers of them. With ``flying``, the rows of a team
        whose agents failed act at their places on the ring of the flying agents and hear their neighbours there."""
        shape = np.shape(observation)
        if len(shape) == 0:
            raise ValueError(f"observations must be rows of one agent's observation each, got an array of shape {shape}")
        rows = np.asarray(observation).reshape(-1, shape[-1])
        n_agents, received = self.config.n_agents, None
        agents, neighbours = np.arange(len(rows)) % n_agents, None
        if flying is not None and not np.all(flying):
            agents, neighbours = flying_rows(np.asarray(flying, dtype=bool).reshape(-1), n_agents)
        if self.message_size:
            state, sent = state_pair(self.describe(), state)
            if channel is not None:
                silent = np.zeros((len(rows), self.message_size), np.float32)
                received = channel.deliver(silent if sent is None else sent, neighbours)
            elif sent is not None:
                keep = 1.0 if episode_start is None else 1.0 - np.asarray(episode_start, np.float32).reshape(-1, 1)
                ring = ring_rows([n_agents] * (len(rows) // n_agents)) if neighbours is None else neighbours
                received = (np.asarray(sent, np.float32) * keep)[ring]
        step = self.agent_step(rows, agents, state, episode_start, received, deterministic)
        actions = step.action.reshape(*shape[:-1], 2)
        return actions, ((step.state, step.message) if self.message_size else step.state)

    def agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        received: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> AgentStep:
        """Actions ``(k, 2)``, next state and sent messages of rows of any agents (see :class:`TeamPolicy`): the inputs
        checked here, then the subclass's :meth:`_agent_step`.

        :raises ValueError: one line: observations of the wrong shape or not finite, agent indices that do not match
            the rows, a state or received messages that are not finite, messages for a policy whose agents send none
        """
        rows = np.asarray(observations)
        rows = rows[None] if rows.ndim == 1 else rows
        size = observation_size(self.config)
        if rows.ndim != 2 or rows.shape[1] != size:
            raise ValueError(
                f"{self.describe()} reads observations of {size} features per agent (the layout of its task), got an "
                f"array of shape {np.shape(observations)}"
            )
        if not np.isfinite(rows).all():
            raise ValueError(f"{self.describe()}: the observations hold NaN or infinite values")
        agents = np.asarray(agents)
        agents = agents.reshape(-1) if agents.ndim < 2 else agents
        if len(agents) != len(rows) or (agents.ndim != 1 and agents.shape[1:] != (2,)):
            raise ValueError(
                f"{self.describe()}: agents of shape {np.shape(agents)} for {len(rows)} observation rows (one index, or "
                "one row (place, ring size), per observation row)"
            )
        check_state(self.describe(), state)
        heard = self.received_messages(received, len(rows))
        return self._agent_step(rows, agents, state, episode_start, heard, deterministic)

    @abstractmethod
    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """:meth:`agent_step` of checked inputs: ``(k, obs_dim)`` finite rows, ``(k,)`` agent indices, a finite state,
        and ``received`` as ``(k, 2 M)`` float32 (or ``None``)."""

    @abstractmethod
    def fit(self, config: FormationConfig) -> Policy:
        """A policy acting in envs of ``config`` (``self`` if it already does); :func:`check_fit` decides.

        :raises ValueError: the policy cannot act there
        """

    def received_messages(self, received: np.ndarray | None, rows: int) -> np.ndarray | None:
        """``received`` as float32 ``(rows, 2 M)`` (``None`` stays ``None``), checked.

        :raises ValueError: messages of another shape, with NaN or infinite values, or messages for a policy whose
            agents send none
        """
        size = self.message_size
        if received is None:
            return None
        if not size:
            raise ValueError(f"{self.describe()} is a policy whose agents send no messages: give no received messages")
        array = np.asarray(received, np.float32)
        if array.size != rows * 2 * size or array.ndim == 0 or array.shape[0] != rows:
            raise ValueError(f"{self.describe()} needs received messages of shape ({rows}, 2, {size}), got {array.shape}")
        if not np.isfinite(array).all():
            raise ValueError(f"{self.describe()}: the received messages hold NaN or infinite values")
        return array.reshape(rows, 2 * size)

    def describe(self) -> str:
        """The policy, for messages: its source file if it has one, else its class."""
        source = getattr(self, "source", None)
        return str(source) if source is not None else type(self).__name__


@functools.lru_cache(maxsize=64)
def observation_size(config: FormationConfig) -> int:
    """Features of one agent's observation in envs of ``config``."""
    return sum(field.size for field in observation_fields(config))


def ring_places(agents: np.ndarray, n_agents: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's place on its ring and the ring's size, from the agents of :meth:`Policy.agent_step`.

    :param agents: ``(k,)`` agent indices (every agent of the team of ``n_agents`` flies), or ``(k, 2)`` rows (place,
        ring size) of a team whose agents failed (:func:`~sb3_formation.env.geometry.flying_rows`)
    :return: ``(k,)`` places and ``(k,)`` ring sizes
    """
    agents = np.asarray(agents, dtype=np.int64)
    if agents.ndim == 1:
        return agents, np.full(len(agents), n_agents)
    return agents[:, 0], agents[:, 1]


class RingShape(NamedTuple):
    """The reference formation of a ring of some size in a task (:func:`ring_shape`)."""

    bearings: np.ndarray  #: ``(size, 2, 2)`` reference bearings g_j^{i,ref} of each place (Table 5.2 for n = 6)
    vertices: np.ndarray  #: ``(size, 2)`` each place on the reference polygon of circumradius 1 (place 0 at the bottom)
    circumradius: float  #: the starting polygon's circumradius (m)
    side_length: float  #: the starting polygon's side (m)
    beta_ref_deg: float  #: the reference angle beta^ref (deg): the polygon's interior angle


@functools.lru_cache(maxsize=64)
def ring_shape(config: FormationConfig, size: int) -> RingShape:
    """The reference formation of a ring of ``size`` agents in the task: the task's own for ``size`` = n, that of
    the flying agents' number in a team whose agents failed."""
    ring = config if size == config.n_agents else config.replace(n_agents=size)
    return RingShape(
        reference_bearings(size),
        reference_polygon(size, 1.0),
        ring.start_circumradius,
        ring.start_side_length,
        ring.beta_ref_deg,
    )


def ring_groups(agents: np.ndarray, n_agents: int) -> list[tuple[np.ndarray | slice, np.ndarray, int]]:
    """The rows of :meth:`Policy.agent_step`'s ``agents`` grouped by the size of their ring: (rows, their places, the
    size) for each size (rows ``slice(None)`` when every row's ring is the team's of ``n_agents``)."""
    places, sizes = ring_places(agents, n_agents)
    if (sizes == n_agents).all():
        return [(slice(None), places, n_agents)]
    return [(sizes == size, places[sizes == size], size) for size in np.unique(sizes).tolist()]


def check_state(who: str, state: Any) -> None:
    """Refuse a policy's state unless it is numbers, all finite (arrays, nested in tuples or lists; ``None`` parts).

    :raises ValueError: one line naming ``who``
    """
    if state is None:
        return
    if isinstance(state, tuple | list):
        for part in state:
            check_state(who, part)
        return
    try:
        finite = bool(np.isfinite(np.asarray(state, dtype=np.float64)).all())
    except (TypeError, ValueError):
        raise ValueError(f"{who}: the state must be the arrays the policy returned, got a {type(state).__name__}") from None
    if not finite:
        raise ValueError(f"{who}: the state holds NaN or infinite values")


def state_pair(who: str, state: Any) -> tuple[Any, Any]:
    """A state that is a pair (e.g. a residual policy's: the correction's state, the controller's memory), split;
    ``None`` gives ``(None, None)``.

    :raises ValueError: one line: a state that is not the pair the policy returned
    """
    if state is None:
        return None, None
    if not (isinstance(state, tuple | list) and len(state) == 2):
        raise ValueError(f"{who}: the state must be the pair the policy returned, got {type(state).__name__}")
    return state[0], state[1]


def cell_state(who: str, state: Any, parts: Sequence[str], shape: tuple[int, ...]) -> list[np.ndarray]:
    """A recurrent actor's state as float32 arrays, one per part (zeros if ``state`` is ``None``).

    :param who: the policy, for the message
    :param parts: the state's parts (``hidden``, and ``cell`` for an LSTM)
    :param shape: each part's shape, ``(1, rows, hidden)``
    :raises ValueError: one line: a state that is not that many arrays of that shape
    """
    if state is None:
        return [np.zeros(shape, np.float32) for _ in parts]
    arrays = [np.asarray(part, np.float32) for part in state] if isinstance(state, tuple | list) else []
    if len(arrays) != len(parts) or any(array.shape != shape for array in arrays):
        got = [array.shape for array in arrays] if arrays else type(state).__name__
        raise ValueError(f"{who} needs a state of {len(parts)} arrays of shape {shape} ({', '.join(parts)}), got {got}")
    return arrays


def no_messages(rows: int) -> np.ndarray:
    """The ``(rows, 0)`` float32 messages of agents that send none."""
    return np.zeros((rows, 0), np.float32)


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


class Controller(Policy):
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
        :meth:`_fit_task` derives what depends on the task. A controller reads its observation's fields by name and
        acts through the task's dynamics, so it fits every task."""
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

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """:meth:`act` on rows of any agents, clipped to [-1, 1], as float32 ``(k, 2)``; a memoryless controller's
        state is ``None`` (one with memory overrides this); its agents send no messages."""
        observations = np.asarray(observations, dtype=np.float64)
        actions = np.clip(self.act(observations, agents, deterministic), -1.0, 1.0).astype(np.float32)
        return AgentStep(actions, None, no_messages(len(observations)))

    @abstractmethod
    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        """Actions ``(k, 2)`` in [-1, 1] (fractions of F_max) for ``(k, obs_dim)`` raw observations.

        :param observations: one row per agent, fields as in :attr:`layout`
        :param agents: ``(k,)`` each row's agent index in its team (0 to n - 1)
        :param deterministic: act without noise (for controllers that have any)
        """
