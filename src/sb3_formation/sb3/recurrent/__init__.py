"""Recurrent PPO without sb3-contrib, split as sb3-contrib splits it: policies, buffers, the algorithm."""

from sb3_formation.sb3.recurrent.ppo import RecurrentFormationPolicy, RecurrentFormationPPO, RecurrentRolloutBuffer

__all__ = ["RecurrentFormationPPO", "RecurrentFormationPolicy", "RecurrentRolloutBuffer"]
