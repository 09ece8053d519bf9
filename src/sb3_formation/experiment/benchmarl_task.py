"""The formation task in BenchMARL (``docs/export.md`` "BenchMARL"): its algorithms (MAPPO, IPPO, ...) train on the
PettingZoo env through TorchRL's ``PettingZooWrapper``.

BenchMARL, TorchRL and torchvision are not dependencies of the package: they live in the integrations environment
(``make test-integrations``), whose torch and torchvision are chosen to import together. This module imports them when
it is imported.

``FormationTask.CH5_BEARING.get_task({"stage": 3, "max_steps": 200})`` is a BenchMARL task: the keys are
:class:`~sb3_formation.env.config.FormationConfig` fields that change the thesis task of that name.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

from benchmarl.environments.common import Task, TaskClass
from torchrl.data import Composite
from torchrl.envs import EnvBase
from torchrl.envs.libs.pettingzoo import PettingZooWrapper

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv


class FormationTaskClass(TaskClass):
    """A thesis task (the enum member's name, e.g. ``CH5_BEARING`` -> ``ch5-bearing``) with the config's changes, as
    BenchMARL builds its envs: one team per env, all its agents in the group ``agent`` (one shared policy with
    BenchMARL's ``share_policy_params``), continuous actions, the team's info values under ``info``."""

    def formation_config(self) -> FormationConfig:
        """The task configuration: the thesis task of :attr:`name` with :attr:`config`'s field changes."""
        return FormationConfig.task(self.name.lower().replace("_", "-"), **self.config)

    def get_env_fun(self, num_envs: int, continuous_actions: bool, seed: int | None, device: Any) -> Callable[[], EnvBase]:
        """A maker of one team's TorchRL env (BenchMARL runs ``num_envs`` of them in a ``SerialEnv``)."""
        config = self.formation_config()

        def make() -> EnvBase:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # TorchRL names the PettingZoo version it was tested with
                return PettingZooWrapper(FormationEnv(config), categorical_actions=False, seed=seed, device=device)

        return make

    def supports_continuous_actions(self) -> bool:
        return True

    def supports_discrete_actions(self) -> bool:
        return False

    def has_render(self, env: EnvBase) -> bool:
        return False

    def max_steps(self, env: EnvBase) -> int:
        return self.formation_config().max_steps

    def group_map(self, env: EnvBase) -> dict[str, list[str]]:
        return env.group_map

    def _group_entries(self, env: EnvBase, key: str) -> Composite:
        """The observation spec with only ``key`` in each group."""
        spec = env.observation_spec.clone()
        for group in self.group_map(env):
            for name in list(spec[group].keys()):
                if name != key:
                    del spec[group][name]
        return spec

    def observation_spec(self, env: EnvBase) -> Composite:
        return self._group_entries(env, "observation")

    def info_spec(self, env: EnvBase) -> Composite | None:
        return self._group_entries(env, "info")

    def state_spec(self, env: EnvBase) -> Composite | None:
        return None

    def action_spec(self, env: EnvBase) -> Composite:
        return env.full_action_spec

    def action_mask_spec(self, env: EnvBase) -> Composite | None:
        return None

    @staticmethod
    def env_name() -> str:
        return "sb3_formation"


class FormationTask(Task):
    """The thesis tasks (:data:`~sb3_formation.env.config.TASKS`) as BenchMARL tasks."""

    CH4_INDIVIDUAL = None
    CH4_TEAM = None
    CH5_ANGLE = None
    CH5_BEARING = None

    @staticmethod
    def associated_class() -> type[FormationTaskClass]:
        return FormationTaskClass
