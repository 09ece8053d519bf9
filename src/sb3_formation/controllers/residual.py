"""Residual policies: a controller's action plus a bounded learned correction.

``a = clip(a_base + scale * a_correction, -1, 1)``: the correction (a policy's action in [-1, 1]^2) moves the
controller's action by at most ``scale`` (a fraction of F_max) per component. With a zero correction the residual
policy is the controller. The same sum acts in training (:class:`~sb3_formation.sb3.residual.ResidualVecEnv`) and
in evaluation (:class:`ResidualPolicy`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sb3_formation.controllers.base import Controller, TeamPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.utils.checks import is_number


def check_residual_scale(scale: Any) -> float:
    """``scale`` as a float, if it is a number in (0, 2] (2 spans the whole action box).

    :raises ValueError: it is not
    """
    if not (is_number(scale) and 0 < scale <= 2):
        raise ValueError(f"the residual scale must be a number in (0, 2] (a fraction of F_max), got {scale!r}")
    return float(scale)


def add_correction(base: np.ndarray, correction: np.ndarray, scale: float) -> np.ndarray:
    """``clip(base + scale * clip(correction, -1, 1), -1, 1)`` as float32 actions.

    :param base: ``(k, 2)`` the controller's actions
    :param correction: ``(k, 2)`` the learned corrections (clipped to [-1, 1] first, as the env would)
    :param scale: the correction's bound, a fraction of F_max
    """
    correction = np.clip(np.asarray(correction, dtype=np.float64).reshape(base.shape), -1.0, 1.0)
    return np.clip(base + scale * correction, -1.0, 1.0).astype(np.float32)


class ResidualPolicy:
    """A controller plus a policy's bounded correction, on the policy seam (raw team observations).

    :param base: the controller
    :param correction: the policy whose actions are the corrections (e.g. a trained model)
    :param scale: the correction's bound, a fraction of F_max
    """

    def __init__(self, base: Controller, correction: TeamPolicy, scale: float) -> None:
        self.base, self.correction, self.scale = base, correction, check_residual_scale(scale)

    @property
    def config(self) -> FormationConfig:
        return self.correction.config

    @property
    def source(self) -> Any:
        """The correction's model file, if any (it records the controller, its gains and the scale too)."""
        return getattr(self.correction, "source", None)

    def fit(self, config: FormationConfig) -> ResidualPolicy:
        """The residual policy acting in envs of ``config`` (both parts fitted)."""
        base, correction = self.base.fit(config), self.correction.fit(config)
        if base is self.base and correction is self.correction:
            return self
        return ResidualPolicy(base, correction, self.scale)

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        """The controller's actions plus the scaled corrections; the state is the pair (the correction's, the
        controller's)."""
        correction_state, base_state = (None, None) if state is None else state
        correction, correction_state = self.correction.predict(observation, correction_state, episode_start, deterministic)
        base, base_state = self.base.predict(observation, base_state, episode_start, deterministic)
        return add_correction(base.astype(np.float64), correction, self.scale), (correction_state, base_state)
