"""sb3-formation: one shared Stable-Baselines3 PPO policy flies a team of robots in formation around obstacles."""

from .config import PRESETS, REWARD_TERMS, FormationConfig
from .env import FormationEnv
from .scenarios import PlacementError, Scenario

__all__ = ["PRESETS", "REWARD_TERMS", "FormationConfig", "FormationEnv", "PlacementError", "Scenario"]
__version__ = "0.1.0"
