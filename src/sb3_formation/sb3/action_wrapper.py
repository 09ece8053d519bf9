"""The base of the VecEnv wrappers that change each slot's action from the raw observation the slot last returned."""

from __future__ import annotations

from abc import abstractmethod
from typing import TYPE_CHECKING, cast

import numpy as np
from stable_baselines3.common.vec_env import VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

if TYPE_CHECKING:
    from sb3_formation.sb3.vec_env import FormationVecEnv


class ActionVecEnvWrapper(VecEnvWrapper):
    """Checks the slots' actions and gives the wrapped env the actions :meth:`_env_actions` makes of them and of each
    slot's last raw observation (the residual sum, the safety filter). Wrap the
    :class:`~sb3_formation.sb3.vec_env.FormationVecEnv` itself, or another such wrapper, below any normaliser.

    :param venv: the formation VecEnv (raw observations; with team observations the first ``agent_obs_dim`` columns)
    """

    venv: FormationVecEnv

    def __init__(self, venv: FormationVecEnv) -> None:
        super().__init__(venv)
        #: features of one agent's own observation (the first columns of a slot's observation)
        self.agent_obs_dim: int = venv.agent_observation_dim
        self._observations: np.ndarray | None = None

    def reset(self) -> VecEnvObs:
        self._observations = cast(np.ndarray, self.venv.reset())  # a Box's observations
        return self._observations

    def step_async(self, actions: np.ndarray) -> None:
        if self._observations is None:
            raise RuntimeError("reset() the env before stepping it")
        actions = self.venv.checked_actions(actions)
        self.venv.step_async(self._env_actions(self._observations[:, : self.agent_obs_dim], actions))

    def step_wait(self) -> VecEnvStepReturn:
        observations, rewards, dones, infos = self.venv.step_wait()
        self._observations = cast(np.ndarray, observations)  # a Box's observations
        return observations, rewards, dones, infos

    @abstractmethod
    def _env_actions(self, observations: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """The actions the wrapped env receives.

        :param observations: ``(num_envs, agent_obs_dim)`` each slot's last raw observation (its own columns)
        :param actions: ``(num_envs, 2)`` the slots' checked actions (float64)
        """
