"""Training a residual policy: the VecEnv wrapper that adds a controller's action to the policy's correction."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast

import numpy as np
from stable_baselines3.common.vec_env import VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from sb3_formation.controllers.base import Controller
from sb3_formation.controllers.residual import add_correction, check_residual_scale

if TYPE_CHECKING:
    from sb3_formation.sb3.vec_env import FormationVecEnv


class ResidualVecEnv(VecEnvWrapper):
    """Makes the agent's action a bounded correction of a controller's: the env receives
    ``clip(a_controller + scale * a, -1, 1)``, the controller acting on the raw observations (wrap the
    :class:`~sb3_formation.sb3.vec_env.FormationVecEnv` itself, below any normaliser). In teams of several sizes each
    team's agents are controlled by the controller fitted to its size.

    :param venv: the formation VecEnv (raw observations; with team observations the first ``agent_obs_dim`` columns)
    :param base: the controller, acting in the env's task
    :param scale: the correction's bound, a fraction of F_max
    """

    venv: FormationVecEnv

    def __init__(self, venv: FormationVecEnv, base: Controller, scale: float) -> None:
        super().__init__(venv)
        self.base, self.scale = base, check_residual_scale(scale)
        self.agent_obs_dim: int = venv.agent_observation_dim
        #: each team task's controller and the slots of its teams (whole teams, agent 0 first, as ``predict`` expects)
        self._controllers = [(base.fit(config), slots) for config, slots in venv.slots_by_task().items()]
        #: each controller's state (its memory of its slots, ``None`` for a memoryless one), carried across steps
        self._states: list[Any] = [None] * len(self._controllers)
        self._observations: np.ndarray | None = None
        self._starts = np.ones(venv.num_envs, dtype=bool)  # the slots whose observation starts an episode

    def reset(self) -> VecEnvObs:
        self._observations = cast(np.ndarray, self.venv.reset())  # a Box's observations
        self._starts[:] = True
        return self._observations

    def step_async(self, actions: np.ndarray) -> None:
        if self._observations is None:
            raise RuntimeError("reset() the env before stepping it")
        actions = self.venv.checked_actions(actions)
        own = self._observations[:, : self.agent_obs_dim]
        base = np.empty((len(own), 2))
        for group, (controller, slots) in enumerate(self._controllers):
            base[slots], self._states[group] = controller.predict(own[slots], self._states[group], self._starts[slots])
        self.venv.step_async(add_correction(base, actions, self.scale))

    def step_wait(self) -> VecEnvStepReturn:
        observations, rewards, dones, infos = self.venv.step_wait()
        self._observations = cast(np.ndarray, observations)  # a Box's observations
        self._starts = np.asarray(dones, dtype=bool).copy()  # an ended episode's slot now shows the next one's start
        return observations, rewards, dones, infos
