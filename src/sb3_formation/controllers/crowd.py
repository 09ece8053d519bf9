"""The privileged crowd baseline: ``controller:shrinking`` flies the formation, and navground's ORCA makes each agent's
velocity collision-free among its teammates, the moving obstacles (given their velocities), the static obstacles, the
walls and the border.

Privileged, like the planner: at every step it reads each team's :class:`~sb3_formation.env.state.TeamState` (where
every agent and obstacle is and how fast it moves), which no agent's sensors give. It is the upper baseline of the
scene families with moving obstacles, not a policy a decentralised one could match with its own sensors.

Each step, for each agent: the velocity that the shrinking controller's action commands (``v + a F_max dt / m``,
clamped to v_max) is ORCA's target velocity; ORCA (navground's behaviour, as the pedestrians of
:mod:`~sb3_formation.env.movers` walk with it) returns the collision-free velocity closest to it, seeing the other
agents and the moving obstacles as neighbours with their velocities (each agent of a pair takes half of the avoidance,
as ORCA assumes of its neighbours), the static circles as discs and each capsule wall as its two long sides and its
two round ends; the action is what commands that velocity, clipped to [-1, 1]. Holonomic agents only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import navground.core as crowd_core
import numpy as np

from sb3_formation.controllers.base import AgentStep, check_gains
from sb3_formation.controllers.shrinking import ShrinkingController
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.state import TeamState


@dataclass(frozen=True)
class CrowdGains:
    """Gains of :class:`CrowdController`'s ORCA (the shrinking controller keeps its defaults).

    :param time_horizon: (s) how far ahead ORCA avoids the other agents and the moving obstacles
    :param static_time_horizon: (s) and the static obstacles, walls and border
    :param safety_margin: (m) gap ORCA keeps beyond the agents' radii
    :param avoid_teammates: ORCA also sees the agent's teammates (else the shrinking controller alone keeps them apart)
    """

    time_horizon: float = 5.0
    static_time_horizon: float = 5.0
    safety_margin: float = 0.02
    avoid_teammates: bool = False

    def __post_init__(self) -> None:
        check_gains(self)


class CrowdController(ShrinkingController):
    """``controller:shrinking`` made collision-free by ORCA among every agent and obstacle, their velocities known
    (privileged; see the module docstring).

    :param config: the task configuration (holonomic agents)
    :param gains: keyword values of :class:`CrowdGains`
    """

    #: Reads every team's state at every step (:meth:`observe_states`): not a decentralised policy.
    privileged = True

    def __init__(self, config: FormationConfig, **gains: float) -> None:
        super().__init__(config)
        self.orca = self._take_gains(CrowdGains, gains)
        self.states: dict[int, TeamState] = {}

    def _fit_task(self) -> None:
        super()._fit_task()
        if self.config.dynamics != "holonomic":
            raise ValueError(f"controller:crowd steers holonomic agents; this task's are {self.config.dynamics}")
        self.states = {}

    def start_episodes(self, teams: Sequence[int], states: Sequence[TeamState]) -> None:
        """Read the new episodes' states (as :meth:`observe_states`)."""
        self.observe_states(teams, states)

    def observe_states(self, teams: Sequence[int], states: Sequence[TeamState]) -> None:
        """Read where every agent and obstacle of ``teams`` is now, and how fast it moves.

        :param teams: the teams (row k of :meth:`predict` belongs to team k // n)
        :param states: each team's state now
        """
        for team, state in zip(teams, states):
            self.states[int(team)] = state

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """The shrinking controller's step, each action then made collision-free for whole teams' rows (row k: agent
        k % n of team k // n) whose state was read; other rows keep the shrinking controller's action."""
        step = super()._agent_step(observations, agents, state, episode_start, received, deterministic)
        actions, n_agents = step.action.astype(np.float64), self.config.n_agents
        for team in range(len(observations) // n_agents):
            if team in self.states:
                rows = slice(team * n_agents, (team + 1) * n_agents)
                actions[rows] = self.avoid(self.states[team], actions[rows])
        return AgentStep(actions.astype(np.float32), step.state, step.message)

    def avoid(self, state: TeamState, actions: np.ndarray) -> np.ndarray:
        """A team's ``actions`` ``(n, 2)`` made collision-free by ORCA in ``state`` (see the module docstring)."""
        config, gains = self.config, self.orca
        push = config.force_max * config.dt / config.agent_mass  # m/s of a unit action over a step
        targets = state.velocities + actions * push
        speeds = np.linalg.norm(targets, axis=1, keepdims=True)
        targets *= np.minimum(1.0, config.v_max / np.maximum(speeds, 1e-300))
        velocities = np.zeros((len(state.obstacles), 2)) if state.obstacle_velocities is None else state.obstacle_velocities
        first_mover = len(state.obstacles) - state.moving
        movers = [
            crowd_core.Neighbor(circle[:2], circle[2], velocity, -1)
            for circle, velocity in zip(state.obstacles[first_mover:], velocities[first_mover:])
        ]
        discs = [crowd_core.Disc(circle[:2], circle[2]) for circle in state.obstacles[:first_mover]]
        lines = _border_lines(config.world_width, config.world_height)
        for x0, y0, x1, y1, thickness in state.walls:
            start, end = np.array([x0, y0]), np.array([x1, y1])
            along = (end - start) / max(float(np.linalg.norm(end - start)), 1e-12)
            side = np.array([-along[1], along[0]]) * thickness / 2
            lines += [crowd_core.LineSegment(start + side, end + side), crowd_core.LineSegment(start - side, end - side)]
            discs += [crowd_core.Disc(start, thickness / 2), crowd_core.Disc(end, thickness / 2)]
        safe = np.empty_like(targets)
        for agent in range(state.n_agents):
            behavior = crowd_core.behaviors.ORCABehavior(
                kinematics=crowd_core.kinematics.OmnidirectionalKinematics(max_speed=config.v_max),
                radius=config.agent_radius,
            )
            behavior.time_horizon, behavior.static_time_horizon = gains.time_horizon, gains.static_time_horizon
            behavior.safety_margin = gains.safety_margin
            behavior.position, behavior.velocity = state.positions[agent], state.velocities[agent]
            behavior.target = crowd_core.Target.Velocity(targets[agent])
            teammates = [
                crowd_core.Neighbor(state.positions[other], config.agent_radius, state.velocities[other], 0)
                for other in range(state.n_agents)
                if other != agent and gains.avoid_teammates
            ]
            environment = cast(crowd_core.GeometricState, behavior.environment_state)  # ORCA's kind of state
            environment.neighbors = teammates + movers
            environment.static_obstacles = discs
            environment.line_obstacles = lines
            safe[agent] = np.asarray(behavior.compute_cmd(config.dt).velocity, dtype=np.float64)
        result: np.ndarray = np.clip((safe - state.velocities) / push, -1.0, 1.0)
        return result


def _border_lines(width: float, height: float) -> list[crowd_core.LineSegment]:
    """The world's border as four segments."""
    corners = [(0.0, 0.0), (width, 0.0), (width, height), (0.0, height)]
    return [crowd_core.LineSegment(start, end) for start, end in zip(corners, corners[1:] + corners[:1])]
