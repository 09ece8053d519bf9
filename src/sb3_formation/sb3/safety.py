"""Shielded training: the VecEnv wrapper that passes every slot's action through the safety filter."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from sb3_formation.safety.filter import SafetyFilter, SafetyGains, SentCommands
from sb3_formation.safety.policy import FilterTally
from sb3_formation.sb3.action_wrapper import ActionVecEnvWrapper

if TYPE_CHECKING:
    from sb3_formation.sb3.vec_env import FormationVecEnv


class SafetyVecEnv(ActionVecEnvWrapper):
    """The env applies the filtered action, PPO keeps its own ("shielded" PPO): each slot's action passes through the
    :class:`~sb3_formation.safety.filter.SafetyFilter` of its team's task, on the raw observation the slot last
    returned (wrap the :class:`~sb3_formation.sb3.vec_env.FormationVecEnv` itself, below a residual wrapper and any
    normaliser). With ``penalty`` > 0 each agent's reward loses ``penalty |a_safe - a|``. When a team's episode ends its
    ``formation_episode`` info gains what the filter did in it (the keys of
    :data:`~sb3_formation.safety.policy.SAFETY_METRIC_KEYS`), which the metrics callback logs to TensorBoard.

    :param venv: the formation VecEnv (raw observations; with team observations the first ``agent_obs_dim`` columns)
    :param gains: the filter's gains (default :class:`SafetyGains`)
    :param penalty: reward lost per unit of the change of an action (>= 0)
    """

    def __init__(self, venv: FormationVecEnv, gains: SafetyGains | None = None, penalty: float = 0.0) -> None:
        super().__init__(venv)
        if not penalty >= 0:
            raise ValueError(f"the safety penalty must be >= 0, got {penalty!r}")
        self.penalty = float(penalty)
        #: each team task's filter and the slots of its teams
        self._filters = [(SafetyFilter(config, gains), slots) for config, slots in venv.slots_by_task().items()]
        self.tally = FilterTally(venv.num_envs)
        #: the actions each slot sent, for the filters' prediction over a declared delay
        self.sent = SentCommands(max(safety.bounds.horizon for safety, _ in self._filters))
        self._change = np.zeros(venv.num_envs)

    def reset(self) -> VecEnvObs:
        observations = super().reset()
        self.tally.resize(self.num_envs)
        return observations

    def _env_actions(self, observations: np.ndarray, actions: np.ndarray) -> np.ndarray:
        safe = np.empty((len(observations), 2))
        sent = self.sent.rows(len(observations), None)
        for safety, slots in self._filters:
            safe[slots], report = safety.filter(observations[slots], actions[slots], sent[slots])
            self._change[slots] = report.change
            self.tally.add(report, slots)
        self.sent.add(safe)
        return safe

    def step_wait(self) -> VecEnvStepReturn:
        observations, rewards, dones, infos = super().step_wait()
        if self.penalty:
            rewards = (rewards - self.penalty * self._change).astype(np.float32)
        for slot, info in enumerate(infos):
            if "formation_episode" in info:  # the team's first slot: its episode ended, the next starts now
                team = self.venv.team_slots(self.venv.slot_team(slot))
                info["formation_episode"] = {**info["formation_episode"], **self.tally.metrics(team)}
                self.tally.restart(team)
                self.sent.actions[team] = 0.0
        return observations, rewards, dones, infos
