"""The random controller: every action uniform in [-1, 1]^2, a baseline and a smoke test."""

from __future__ import annotations

import numpy as np

from sb3_formation.controllers.base import Controller
from sb3_formation.env.config import FormationConfig


class RandomController(Controller):
    """Uniformly random actions from the controller's own generator (also when ``deterministic`` is asked for).

    :param config: the task configuration
    :param seed: seed of the generator (``None``: random)
    """

    def __init__(self, config: FormationConfig, seed: int | None = None) -> None:
        super().__init__(config)
        self.gains = {"seed": seed}
        self.rng = np.random.default_rng(seed)

    def seed(self, seed: int | None) -> None:
        """Restart the generator from ``seed`` (evaluation calls this with its seed, so its episodes repeat)."""
        self.rng = np.random.default_rng(seed)

    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, (len(observations), 2))
