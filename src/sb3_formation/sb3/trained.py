"""``TrainedPolicy``: a trained SB3 model paired with its normaliser statistics, acting on raw observations.

It is the adapter between the policy contract (:class:`~sb3_formation.controllers.base.Policy`: raw observations of
any agents) and what the network was trained on: observations scaled by the frozen statistics and, for a team critic,
each slot's own observation followed by its team's (which only the critic reads: the actor reads the first block).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sb3_formation.controllers.base import AgentStep, Policy, cell_state, check_fit, no_messages
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.observations import observation_fields
from sb3_formation.runtime.onnx_policy import STATE_PARTS
from sb3_formation.sb3.normalization import STATE_KEYS, observation_offset, observation_scale, scale_observations
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent.policies import RecurrentFormationPolicy


@dataclass
class TrainedPolicy(Policy):
    """A trained model with what it needs to act: its task configuration and its normaliser statistics.

    :param model: an SB3 algorithm (its ``policy`` acts) or anything with SB3's ``predict`` on normalised observations
    :param config: the task configuration it was trained in
    :param normalizer_state: :meth:`~sb3_formation.sb3.normalization.ScaleNormalizeVecEnv.state_dict` of its training env
    :param source: the model file it was loaded from, if any
    :param team_sizes: the team sizes it was trained on (default: ``config.n_agents``); a policy trained on several
        acts in teams of any size (its observation does not depend on n), others only in teams of their own size
    """

    model: Any
    config: FormationConfig
    normalizer_state: dict[str, np.ndarray]
    source: Path | None = None
    team_sizes: tuple[int, ...] = ()
    _scale: np.ndarray = field(init=False, repr=False)
    _offset: np.ndarray | None = field(init=False, repr=False)
    _clip: float | None = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.team_sizes = tuple(self.team_sizes) or (self.config.n_agents,)
        missing = [key for key in STATE_KEYS if key not in self.normalizer_state]
        if missing:
            raise ValueError(f"the normaliser statistics lack {missing}")
        self._scale = observation_scale(self.normalizer_state)
        self._offset = observation_offset(self.normalizer_state)
        clip = float(self.normalizer_state["clip_obs"])
        self._clip = None if math.isnan(clip) else clip

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (e.g. for evaluation workers) with the model's policy only: the algorithm holds its training env."""
        return {**self.__dict__, "model": self.policy}

    @property
    def policy(self) -> Any:
        """What acts on normalised observations: the model's SB3 policy, or the model itself."""
        return getattr(self.model, "policy", self.model)

    @property
    def team_observations(self) -> bool:
        """Whether the network reads each slot's whole team (a team critic, thesis fig. 4.3)."""
        return getattr(self.policy, "team_size", None) is not None

    @property
    def any_team_size(self) -> bool:
        """Whether it acts in teams of any size: trained on several, with no team critic (which reads a whole team)."""
        return len(self.team_sizes) > 1 and not self.team_observations

    @property
    def message_size(self) -> int:
        return int(getattr(self.policy, "message_size", 0))

    def fit(self, config: FormationConfig) -> TrainedPolicy:
        """The policy acting in envs of ``config``: ``self``, or (a policy of :attr:`any_team_size` in a team of
        another size) a copy that acts there.

        :raises ValueError: :func:`~sb3_formation.controllers.base.check_fit`'s differences, or normaliser statistics of
            another layout
        """
        check_fit(self.describe(), self.config, config, self.any_team_size)
        mismatch = normalizer_mismatch(self.normalizer_state, config)
        if mismatch is not None:
            raise ValueError(f"the normaliser statistics do not fit this env's observations: {mismatch}")
        return self if config.n_agents == self.config.n_agents else dataclasses.replace(self, config=config)

    def describe(self) -> str:
        return "the model" if self.source is None else str(self.source)

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """The model's actions for raw observations of any agents (scaled by the frozen statistics), its next state
        (a recurrent actor's cell state) and the messages its agents send."""
        rows = np.asarray(observations)
        if self.team_observations:  # the actor reads a slot's own block only; the team's blocks feed the critic
            rows = np.hstack([rows, np.zeros((len(rows), self.config.n_agents * rows.shape[1]), rows.dtype)])
        scaled = scale_observations(rows, self._scale, self._clip, self._offset)
        if isinstance(self.policy, RecurrentFormationPolicy):
            actor, shape = self.policy.actor, (1, len(rows), self.policy.actor.hidden)
            state = None if state is None else tuple(cell_state(self.describe(), state, STATE_PARTS[actor.cell], shape))
            actions, state, message = self.policy.actor_step(scaled, state, episode_start, received, deterministic)
            return AgentStep(actions, state, message)
        if deterministic and isinstance(self.policy, FormationPolicy):  # the same actions, faster
            return AgentStep(self.policy.deterministic_actions(scaled), state, no_messages(len(rows)))
        actions, state = self.policy.predict(scaled, state=state, episode_start=episode_start, deterministic=deterministic)
        return AgentStep(actions, state, no_messages(len(rows)))


def normalizer_mismatch(state: dict[str, np.ndarray], config: FormationConfig) -> str | None:
    """How normaliser statistics differ from the layout of one agent's observation in envs of ``config`` (its size,
    which features are 0/1 flags, the statistics' shapes), or ``None`` if they fit.

    :param state: :meth:`~sb3_formation.sb3.normalization.ScaleNormalizeVecEnv.state_dict` (e.g. a normaliser file's)
    """
    mask = np.concatenate([np.full(field.size, field.binary) for field in observation_fields(config)])
    size = int(np.asarray(state["agent_obs_dim"]))
    if size != mask.size:
        return f"they are for observations of {size} features, the task's have {mask.size}"
    if not np.array_equal(np.asarray(state["binary_mask"]), mask):
        return "their 0/1 flag features are not the task's"
    shapes = {key: np.shape(state[key]) for key in ("mean", "var")}
    if any(shape != (size,) for shape in shapes.values()):
        return f"their statistics have shapes {shapes}, not ({size},)"
    return None
