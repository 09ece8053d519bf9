"""Residual policies: a controller's action plus a bounded learned correction.

``a = clip(a_base + scale * a_correction, -1, 1)``: the correction (a policy's action in [-1, 1]^2) moves the
controller's action by at most ``scale`` (a fraction of F_max) per component. With a zero correction the residual
policy is the controller. :class:`ResidualAdapter` computes the sum (:meth:`ResidualAdapter.corrected`) and carries
the controller's memory wherever a residual policy acts: in evaluation (:class:`ResidualPolicy`), in training
(:class:`~sb3_formation.sb3.residual.ResidualVecEnv`) and in the torch-free runtime
(:class:`~sb3_formation.runtime.OnnxPolicy`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sb3_formation.controllers.base import AgentStep, Controller, Policy, TeamPolicy, state_pair
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


class ResidualAdapter:
    """The controller's side of a residual policy: the controller, its memory, the scale and the sum
    (:func:`add_correction`), for rows of agents whose learned corrections the caller has.

    The memory is carried as Stable-Baselines3 carries a policy's state: :meth:`corrected` returns it, the caller hands it
    back with the next rows (the same rows, in the same order), and ``episode_start`` flags the rows whose episode
    starts now, whose memory the controller resets (``None`` as the memory starts every row's episode; a memoryless
    controller's memory is ``None``). The adapter holds no memory itself: a policy's ``predict`` must start afresh
    when called with ``state=None``, and one adapter serves any number of teams and episodes at once. Each user keeps
    the memory beside its other state:

    - :class:`ResidualPolicy` (evaluation) and :class:`~sb3_formation.runtime.OnnxPolicy` return it as the second
      part of their SB3 state (the learned part's state, the controller's memory) and pass SB3's ``episode_start``;
    - :class:`~sb3_formation.sb3.residual.ResidualVecEnv` (training) has no SB3 state and is the caller itself: it
      keeps one memory per team task and flags the slots whose observation starts an episode (all of them after
      ``reset``, those that ``dones`` flag after a step).

    :param controller: the controller (decentralised: it reads each agent's own observation)
    :param scale: the correction's bound, a fraction of F_max
    :raises ValueError: a scale outside (0, 2]
    """

    def __init__(self, controller: Controller, scale: float) -> None:
        self.controller, self.scale = controller, check_residual_scale(scale)

    def fit(self, config: FormationConfig) -> ResidualAdapter:
        """The adapter acting in envs of ``config`` (its controller fitted; ``self`` if that changes nothing)."""
        controller = self.controller.fit(config)
        return self if controller is self.controller else ResidualAdapter(controller, self.scale)

    def corrected(
        self,
        observations: np.ndarray,
        correction: np.ndarray,
        memory: Any = None,
        episode_start: np.ndarray | None = None,
        agents: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        """The controller's actions plus the scaled corrections, float32 ``(k, 2)``, and the controller's next memory.

        :param observations: ``(k, obs_dim)`` raw observations
        :param correction: ``(k, 2)`` the learned corrections of these rows
        :param memory: what the previous call returned for these rows (``None`` at the start)
        :param episode_start: ``(k,)`` flags: these rows start an episode (their memory is reset)
        :param agents: ``(k,)`` each row's agent index in its team, or ``(k, 2)`` its place and ring size
            (:func:`~sb3_formation.controllers.base.ring_places`); ``None``: the rows are whole teams, row k is agent
            ``k % n`` (the policy seam's order)
        :param deterministic: the controller acts without noise
        """
        rows = np.asarray(observations, dtype=np.float64).reshape(-1, np.shape(observations)[-1])
        agents = np.arange(len(rows)) % self.controller.config.n_agents if agents is None else np.asarray(agents)
        agents = agents.reshape(-1) if agents.ndim < 2 else agents
        base, memory, _ = self.controller.agent_step(rows, agents, memory, episode_start, deterministic=deterministic)
        return add_correction(base.astype(np.float64), correction, self.scale), memory


class ResidualPolicy(Policy):
    """A controller plus a policy's bounded correction, on the policy seam. Its state is the pair (the correction's
    state, the controller's memory); its agents send the correction's messages.

    :param base: the controller
    :param correction: the policy whose actions are the corrections (e.g. a trained model)
    :param scale: the correction's bound, a fraction of F_max
    """

    def __init__(self, base: Controller, correction: TeamPolicy, scale: float) -> None:
        self.residual, self.correction = ResidualAdapter(base, scale), correction

    @property
    def base(self) -> Controller:
        """The controller."""
        return self.residual.controller

    @property
    def scale(self) -> float:
        """The correction's bound, a fraction of F_max."""
        return self.residual.scale

    @property
    def config(self) -> FormationConfig:  # type: ignore[override]  # the correction's: read-only
        return self.correction.config

    @property
    def message_size(self) -> int:
        return self.correction.message_size

    @property
    def source(self) -> Any:
        """The correction's model file, if any (it records the controller, its gains and the scale too)."""
        return getattr(self.correction, "source", None)

    def fit(self, config: FormationConfig) -> ResidualPolicy:
        """The residual policy acting in envs of ``config`` (both parts fitted: the correction's fit decides)."""
        base, correction = self.base.fit(config), self.correction.fit(config)
        if base is self.base and correction is self.correction:
            return self
        return ResidualPolicy(base, correction, self.scale)

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """The controller's actions plus the scaled corrections of the correction's agent step."""
        correction_state, memory = state_pair(self.describe(), state)
        step = self.correction.agent_step(observations, agents, correction_state, episode_start, received, deterministic)
        actions, memory = self.residual.corrected(observations, step.action, memory, episode_start, agents, deterministic)
        return AgentStep(actions, (step.state, memory), step.message)
