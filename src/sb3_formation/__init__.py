"""sb3-formation: one shared Stable-Baselines3 PPO policy flies a team of robots in formation around obstacles."""

from .config import PRESETS, REWARD_TERMS, FormationConfig
from .env import FormationEnv
from .normalization import ScaleNormalizeVecEnv
from .policies import FormationPolicy
from .scenarios import PlacementError, Scenario
from .vec_env import FormationVecEnv, make_formation_vec_env

__all__ = [
    "PRESETS",
    "REWARD_TERMS",
    "FormationConfig",
    "FormationEnv",
    "FormationPolicy",
    "FormationVecEnv",
    "PlacementError",
    "ScaleNormalizeVecEnv",
    "Scenario",
    "make_formation_vec_env",
]
__version__ = "0.1.0"
