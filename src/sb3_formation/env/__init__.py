"""The formation task: configuration, world, sensors, observations, rewards, scenarios and the PettingZoo env.

This layer needs numpy, numba, Pymunk, Gymnasium, PettingZoo and Pillow only: importing it loads no torch, no
Stable-Baselines3 and no plotting code.
"""

from sb3_formation.env.config import REWARD_TERMS, TASKS, FormationConfig
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.scenarios import PlacementError, Scenario

__all__ = ["REWARD_TERMS", "TASKS", "FormationConfig", "FormationEnv", "PlacementError", "Scenario"]
