"""Training a residual policy: the VecEnv wrapper that adds a controller's action to the policy's correction."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from sb3_formation.controllers.base import Controller
from sb3_formation.controllers.residual import ResidualAdapter
from sb3_formation.sb3.action_wrapper import ActionVecEnvWrapper

if TYPE_CHECKING:
    from sb3_formation.sb3.vec_env import FormationVecEnv


class ResidualVecEnv(ActionVecEnvWrapper):
    """Makes the agent's action a bounded correction of a controller's: the env receives
    ``clip(a_controller + scale * a, -1, 1)`` (:class:`~sb3_formation.controllers.residual.ResidualAdapter`), the
    controller acting on the raw observations (wrap the :class:`~sb3_formation.sb3.vec_env.FormationVecEnv` itself,
    below any normaliser). In teams of several sizes each team's agents are controlled by the controller fitted to its
    size. The controller's memory of each slot is carried from step to step and reset where an episode starts: at
    :meth:`reset` and in the slots that ``dones`` flag (they already show the next episode's first observation).

    :param venv: the formation VecEnv (raw observations; with team observations the first ``agent_obs_dim`` columns)
    :param base: the controller, acting in the env's task
    :param scale: the correction's bound, a fraction of F_max
    """

    def __init__(self, venv: FormationVecEnv, base: Controller, scale: float) -> None:
        super().__init__(venv)
        residual = ResidualAdapter(base, scale)
        #: each team task's adapter and the slots of its teams (whole teams, agent 0 first)
        self._residuals = [(residual.fit(config), slots) for config, slots in venv.slots_by_task().items()]
        #: each adapter's memory of its slots (``None`` for a memoryless controller), carried across steps
        self._memories: list[Any] = [None] * len(self._residuals)
        self._starts = np.ones(venv.num_envs, dtype=bool)  # the slots whose observation starts an episode

    def reset(self) -> VecEnvObs:
        observations = super().reset()
        self._starts[:] = True
        return observations

    def _env_actions(self, observations: np.ndarray, actions: np.ndarray) -> np.ndarray:
        corrected = np.empty((len(observations), 2), dtype=np.float32)
        for group, (residual, slots) in enumerate(self._residuals):
            corrected[slots], self._memories[group] = residual.corrected(
                observations[slots], actions[slots], self._memories[group], self._starts[slots]
            )
        return corrected

    def step_wait(self) -> VecEnvStepReturn:
        observations, rewards, dones, infos = super().step_wait()
        self._starts = np.asarray(dones, dtype=bool).copy()  # an ended episode's slot now shows the next one's start
        return observations, rewards, dones, infos
