"""One agent's observation (thesis Table 3.1) built on board from what a robot knows, and its command.

A robot knows its team's poses and velocities (every teammate's odometry, in one shared world frame), the goal, its
own lidar (:mod:`~sb3_formation.ros.scans`), and what it remembers: its previous action, the step count since the goal
was given, the team's previous velocities and centroid. :class:`AgentObserver` writes from these the row the
simulator writes (:func:`~sb3_formation.env.observations.observation_fields`), with the simulator's own row builder
(:func:`~sb3_formation.env.observations.observation_row`), including the previous reward, which it computes with the
package's reward terms and the coefficients of the policy's last stage. Numpy and the
environment layer only (no rclpy).

What a robot cannot know exactly, and how the observer stands in for it: the gap to the nearest obstacle, which the
reward's collision term compares with d_safe, is the smallest reading of its obstacle channel (the simulator measures
it on its map); a team reward (``team_reward``), which needs every teammate's gap, is refused.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, NamedTuple

import numpy as np

from sb3_formation.env.config import REWARD_TERMS, FormationConfig
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.env.geometry import (
    FormationState,
    flying_ring,
    interior_angle_deg,
    measure_formation,
    reference_bearings,
)
from sb3_formation.env.observations import AgentInputs, RowTask, observation_fields, observation_layout, observation_row
from sb3_formation.env.rewards import combine_rewards, reward_constants, reward_terms

#: The curriculum's last stage, whose reward coefficients a deployed agent observes (all terms on).
FINAL_STAGE = 3
#: The actions an observer keeps for rows that lag behind them (delayed inputs): far more steps than any delay.
KEPT_ACTIONS = 256


class TeamView(NamedTuple):
    """What an agent knows of its team at one instant, in the shared world frame (REP 103: m, m/s, rad)."""

    positions: np.ndarray  #: ``(n, 2)`` every agent's centre, row i agent i
    velocities: np.ndarray  #: ``(n, 2)`` every agent's velocity
    headings: np.ndarray  #: ``(n,)`` every agent's heading (rad, anti-clockwise from +x)


class AgentObserver:
    """Builds one agent's observation rows, step after step, from its team's poses, the goal and its two lidar channels.

    Call :meth:`reset` when a new goal arrives (an episode starts), then per step :meth:`observe` and, with the action
    the policy chose, :meth:`remember`.

    Row k of an episode (its k-th call of :meth:`observe`) holds the action remembered k-th (the one taken at step
    k - 1), as the engine's row of step k does: the last action when every row is acted on once, an older one when
    rows lag behind the actions (inputs delivered late, whose row is acted on again while the episode is younger
    than the delay).

    :param config: the policy's task (from its exported metadata)
    :param agent: the agent's index in its team (ring order, thesis Table 5.2)
    :param stage: the curriculum stage whose reward coefficients give the observed previous reward
    :raises ValueError: a team reward, or an agent index outside the team
    """

    def __init__(self, config: FormationConfig, agent: int, stage: int = FINAL_STAGE) -> None:
        if config.team_reward:
            raise ValueError(
                "a policy trained on the team reward cannot run on board: each agent would need every "
                "teammate's distance to its nearest obstacle"
            )
        if not 0 <= agent < config.n_agents:
            raise ValueError(f"agent index {agent} is outside a team of {config.n_agents} agents (0 to {config.n_agents - 1})")
        self.config, self.agent = config, agent
        self._rewards = reward_constants(config)
        coefficients = config.reward_coefficients(stage)
        self._coefficients = np.array([coefficients[term] for term in REWARD_TERMS])
        self.layout = observation_layout(observation_fields(config))
        self.dim = sum(part.stop - part.start for part in self.layout.values())
        self._model = dynamics_model(config)
        self.reset()

    def set_flying(self, flying: np.ndarray) -> None:
        """The teammates that fly (the others failed): from now on (until :meth:`reset`) the agent observes the ring
        of the flying agents (:func:`~sb3_formation.env.geometry.flying_ring`), as the simulator's agents do after a
        failure: its neighbours, reference bearings and beta^ref, and their centroid.

        :param flying: ``(n,)`` bool, the agent's own entry true
        :raises ValueError: the agent itself is not flying, or fewer than 3 agents fly
        """
        config, flying = self.config, np.asarray(flying, dtype=bool).copy()
        if not flying[self.agent]:
            raise ValueError(f"agent {self.agent} observes only while it flies")
        ring = flying_ring(flying)
        #: ``(n,)`` bool: the teammates that fly; their ring neighbours and reference bearings (Table 5.2 for n)
        self.flying, self.neighbours = flying, ring.neighbours
        self.reference = reference_bearings(config.n_agents)
        self.reference[flying] = reference_bearings(ring.size)[ring.places[flying]]
        self._beta_ref = interior_angle_deg(ring.size)
        self._task = RowTask(
            self.neighbours, self.reference, float(config.d_ref), float(config.eta_c), bool(config.observe_reference_bearings)
        )

    def reset(self) -> None:
        """Forget the last episode: no step, no previous action or reward; every teammate flies."""
        self.set_flying(np.ones(self.config.n_agents, dtype=bool))
        self.step = 0
        self.previous_action = np.zeros(2)
        self.previous_reward = 0.0
        self._actions: deque[np.ndarray] = deque(maxlen=KEPT_ACTIONS)  # the last actions remembered
        self._remembered = 0  # actions remembered in this episode
        self._previous: tuple[np.ndarray, np.ndarray, float] | None = None  # velocities, goal offset, goal distance

    def observe(self, team: TeamView, lidar: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """The agent's observation now, ``(dim,)`` float64; counts a step after the first call of an episode.

        :param team: the team now
        :param lidar: ``(2, n_rays)`` the agent's obstacle and agent channels, fractions of the range
            (:func:`~sb3_formation.ros.scans.split_scan`)
        :param goal: ``(2,)`` the goal (m)
        """
        config, agent, goal = self.config, self.agent, np.asarray(goal, dtype=np.float64)
        positions = np.ascontiguousarray(team.positions, dtype=np.float64)
        velocities = np.asarray(team.velocities, dtype=np.float64)
        formation = measure_formation(positions, self.neighbours, self.reference, self._beta_ref, config.d_ref, self.flying)
        offset = goal - formation.centroid
        goal_distance = math.hypot(float(offset[0]), float(offset[1]))
        previous_offset = offset
        if self._previous is not None:  # a step was taken: its reward, as the simulator gives it
            previous_velocities, previous_offset, previous_distance = self._previous
            self.step += 1
            gap = float(lidar[0].min()) * config.lidar_range
            distances, moved = (previous_distance, goal_distance), (previous_velocities, velocities)
            self.previous_reward = self._reward(formation, positions, distances, moved, gap)
            kept = self.step - 1 - (self._remembered - len(self._actions))  # the action of step k - 1, if still kept
            if 0 <= kept < len(self._actions):
                self.previous_action = self._actions[kept]
        self._previous = velocities.copy(), offset, goal_distance
        headings = np.asarray(team.headings, dtype=np.float64)[agent : agent + 1]
        observed = self._model.observed_values(headings)[0]
        inputs = AgentInputs(goal, previous_offset, float(self.step), self.previous_action, self.previous_reward, observed)
        row = np.empty(self.dim)
        lidar = np.asarray(lidar, dtype=np.float64)
        observation_row(row, agent, positions, velocities, formation, lidar, inputs, self._task)
        return row

    def _reward(
        self,
        formation: FormationState,
        positions: np.ndarray,
        goal_distances: tuple[float, float],
        velocities: tuple[np.ndarray, np.ndarray],
        gap: float,
    ) -> float:
        """The agent's reward for the step just taken (eq. 42 with the stage's coefficients, clipped), with the goal
        term of the straight centroid-goal distance (the one every agent observes, :mod:`~sb3_formation.env.progress`).

        :param formation: the team's formation after the step
        :param positions: ``(n, 2)`` the team's positions (m) after the step
        :param goal_distances: the centroid's distance (m) to the goal before and after the step
        :param velocities: the team's velocities (m/s) before and after the step
        :param gap: (m) the agent's distance to the nearest obstacle, from its obstacle channel
        """
        agent, n_agents, flying = self.agent, self.config.n_agents, self.flying
        x, y = positions[agent]
        nearest_agents, gaps = np.full(n_agents, np.inf), np.full(n_agents, np.inf)
        others = [(px, py) for k, (px, py) in enumerate(positions.tolist()) if k != agent and flying[k]]
        nearest_agents[agent] = min(math.hypot(px - x, py - y) for px, py in others)
        gaps[agent] = gap
        terms = reward_terms(
            self.config,
            self.step,
            formation,
            goal_distances[0],
            goal_distances[1],
            velocities[0],
            velocities[1],
            self.neighbours,
            nearest_agents,
            gaps,
            self._rewards,
        )
        return float(combine_rewards(terms, self._coefficients, self.config.reward_clip)[agent])

    def memory(self) -> tuple[Any, ...]:
        """What the observer remembers of the episode (for :meth:`restore`)."""
        return self.step, self.previous_action.copy(), self.previous_reward, self._previous

    def restore(self, memory: tuple[Any, ...]) -> None:
        """Forget the steps since :meth:`memory` gave ``memory`` (a step that was not acted on)."""
        self.step, self.previous_action, self.previous_reward, self._previous = memory

    def remember(self, action: np.ndarray) -> None:
        """Keep the action the agent took (after the safety filter) for the next observation (the row of the next
        step)."""
        self.previous_action = np.asarray(action, dtype=np.float64).reshape(2).copy()
        self._actions.append(self.previous_action)
        self._remembered += 1
