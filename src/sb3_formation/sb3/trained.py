"""``TrainedPolicy``: a trained SB3 model paired with its normaliser statistics, acting on raw observations.

It is the adapter between the policy seam (:class:`~sb3_formation.controllers.base.TeamPolicy`: raw observations of
whole teams) and what the network was trained on: observations scaled by the frozen statistics and, for a team critic,
each slot's own observation followed by its whole team's.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.geometry import ring_rows
from sb3_formation.env.observations import observation_fields
from sb3_formation.env.slots import slot_observations
from sb3_formation.sb3.normalization import STATE_KEYS, observation_offset, observation_scale, scale_observations
from sb3_formation.sb3.policies import FormationPolicy

#: Fields that shape the observation vector: a model only fits envs that agree on them.
OBSERVATION_SHAPING_FIELDS = ("n_agents", "lidar_rays")


@dataclass
class TrainedPolicy:
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

    def fit(self, config: FormationConfig) -> TrainedPolicy:
        """The policy acting in envs of ``config``: ``self``, or (a policy of :attr:`any_team_size` in a team of
        another size) a copy that acts there.

        :raises ValueError: naming every observation-shaping difference, or normaliser statistics of another layout
        """
        shaping = [name for name in OBSERVATION_SHAPING_FIELDS if not (name == "n_agents" and self.any_team_size)]
        differences = [
            f"{name}={getattr(self.config, name)} in the model, {getattr(config, name)} in the env"
            for name in shaping
            if getattr(self.config, name) != getattr(config, name)
        ]
        if differences:
            raise ValueError("the model does not fit this env's observations: " + "; ".join(differences))
        mismatch = normalizer_mismatch(self.normalizer_state, config)
        if mismatch is not None:
            raise ValueError(f"the normaliser statistics do not fit this env's observations: {mismatch}")
        return self if config.n_agents == self.config.n_agents else dataclasses.replace(self, config=config)

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        """The model's actions for raw observations of whole teams (row k: agent ``k % n`` of team ``k // n``)."""
        rows = np.asarray(observation).reshape(-1, self._scale.size)
        scaled = scale_observations(
            slot_observations(rows, self.config.n_agents, self.team_observations), self._scale, self._clip, self._offset
        )
        if deterministic and isinstance(self.policy, FormationPolicy):  # the same actions, faster
            return self.policy.deterministic_actions(scaled), state
        if getattr(self.policy, "message_size", 0):  # its agents hear their ring neighbours in the rows' teams
            neighbours = ring_rows([self.config.n_agents] * (len(rows) // self.config.n_agents))
            return self.policy.predict(scaled, state, episode_start, deterministic, neighbours)
        return self.policy.predict(scaled, state=state, episode_start=episode_start, deterministic=deterministic)


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
