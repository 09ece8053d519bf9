"""``FormationBatch``: many teams of :class:`~sb3_formation.env.formation_env.FormationEnv` stepped together.

A step of every team is: one compiled call for the forces, Pymunk for each team (its own space), then three compiled
calls over the stacked arrays of every agent of every team (formation geometry and nearest gaps; reward terms; lidar,
observations, info values and the episode's running sums), with numpy between them only where the single-team path
uses numpy too (the weighted sum of the reward terms, the team means) or Python (``math.hypot`` for the goal distance),
so that every number is the one :meth:`FormationEnv.step_array` computes, bit for bit (``tests/test_batch.py``).

Each team's :class:`FormationEnv` keeps its world, its scenario generator, its stage and its reset: the batch resets a
team through it, then loads the team's state into its arrays (:meth:`FormationBatch.load`). While the batch steps, the
envs' own episode attributes fall behind; :meth:`FormationBatch.sync` writes a team's back before anyone reads it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np

from sb3_formation.env.config import REWARD_TERMS
from sb3_formation.env.episodes import episode_summary
from sb3_formation.env.formation_env import FormationEnv, agent_infos
from sb3_formation.env.geometry import FormationState, _measure, agent_errors
from sb3_formation.env.observations import _fill_observations
from sb3_formation.env.rewards import _reward_terms, nearest_gaps
from sb3_formation.env.sensors import lidar_ranges
from sb3_formation.env.world import clamp_speed, split_state

_N_TERMS = len(REWARD_TERMS)
#: columns of the info values :meth:`FormationBatch.step` returns: the five errors and distances of :data:`INFO_KEYS`,
#: then the reward terms (:func:`agent_infos` adds the contacts and success)
INFO_VALUES = 5 + _N_TERMS


class FormationBatch:
    """Teams of :class:`FormationEnv` (one task, any team sizes) stepped as one: arrays in, arrays out.

    Agents are stacked one team after the other (team t holds rows ``starts[t]:starts[t + 1]``, agent 0 first).

    :param envs: the teams; their configurations may differ in ``n_agents`` only
    """

    def __init__(self, envs: Sequence[FormationEnv]) -> None:
        self.envs = list(envs)
        if not self.envs:
            raise ValueError("a FormationBatch needs at least one team")
        config = self.config = self.envs[0].config
        for env in self.envs:
            if env.config.replace(n_agents=config.n_agents) != config:
                raise ValueError("the teams of a FormationBatch must share one task (they may differ in n_agents only)")
        #: team sizes, and the first row of each team (and the number of rows, last)
        self.sizes = sizes = np.array([env.config.n_agents for env in self.envs])
        self.starts = np.concatenate([[0], np.cumsum(sizes)])
        n_teams, n_slots = len(sizes), int(self.starts[-1])
        rays, dim = config.lidar_rays, self.envs[0].observation_space("agent_0").shape[0]
        self.observation_dim = dim
        #: team size -> (teams of that size, their agents' rows in team order): the groups of the stacked numpy work
        self._groups = {
            int(size): (teams, np.concatenate([np.arange(self.starts[t], self.starts[t + 1]) for t in teams]))
            for size in np.unique(sizes)
            for teams in [np.flatnonzero(sizes == size)]
        }
        self._single_size = len(self._groups) == 1
        # per-agent constants, stacked: neighbours as indices within the team, reference bearings
        self._neighbours = np.concatenate([env.neighbours for env in self.envs]).astype(np.int64)
        self._reference = np.ascontiguousarray(np.concatenate([env.reference_bearings for env in self.envs]))
        self._directions = self.envs[0].lidar.directions
        # per-team constants
        self._reward_constants = np.stack([env._reward_constants for env in self.envs])
        self._beta_ref = np.array([env.config.beta_ref_deg for env in self.envs])
        self._coefficients = np.zeros((n_teams, _N_TERMS))
        # the episode state of every agent and team
        self.positions = np.zeros((n_slots, 2))
        self.velocities = np.zeros((n_slots, 2))
        self.previous_actions = np.zeros((n_slots, 2))
        self.previous_rewards = np.zeros(n_slots)
        self.contacts = np.zeros((n_slots, 2), dtype=np.int64)  # agents, obstacles touched in the last step
        self.lidar = np.zeros((2, n_slots, rays))
        self.goals = np.zeros((n_teams, 2))
        # every team's lidar layout (Lidar.layout: its obstacles then its agents as circles, who sees which, channels),
        # padded to the widest team's; the obstacles' circles are also what the rewards' nearest gaps measure
        self._lidar_circles = np.zeros((n_teams, 0, 3))
        self._lidar_visible = np.zeros((n_slots, 0), dtype=bool)
        self._lidar_channels = np.zeros((n_teams, 0), dtype=np.int64)
        self._lidar_counts = np.zeros(n_teams, dtype=np.int64)
        self.step_counts = np.zeros(n_teams, dtype=np.int64)
        self.goal_distances = np.zeros(n_teams)
        self.previous_offsets = np.zeros((n_teams, 2))  # c_g^v one step earlier
        self.live = np.zeros(n_teams, dtype=bool)
        # the formation now (FormationState's fields, stacked)
        self.centroids = np.zeros((n_teams, 2))
        self.centroid_distances = np.zeros(n_slots)
        self.neighbour_offsets = np.zeros((n_slots, 2, 2))
        self.neighbour_distances = np.zeros((n_slots, 2))
        self.bearings = np.zeros((n_slots, 2, 2))
        self.angles = np.zeros(n_slots)
        self.angle_errors = np.zeros(n_slots)
        self.bearing_errors = np.zeros((n_slots, 2))
        self.orientation_flags = np.zeros(n_slots, dtype=bool)
        self.range_flags = np.zeros(n_teams, dtype=bool)
        # running sums of every team's episode (as EpisodeStatistics keeps them)
        self.episode_lengths = np.zeros(n_teams, dtype=np.int64)
        self.episode_returns = np.zeros(n_teams)
        self.episode_errors = np.zeros((n_teams, 3))
        self.episode_collisions = np.zeros((n_teams, 2), dtype=np.int64)
        self.episode_terms = np.zeros((n_teams, _N_TERMS))
        self._stale = np.zeros(n_teams, dtype=bool)  # stepped here since the env last saw its state

    @property
    def n_teams(self) -> int:
        return len(self.envs)

    def team_rows(self, team: int) -> slice:
        """The rows of a team's agents, agent 0 first."""
        return slice(int(self.starts[team]), int(self.starts[team + 1]))

    # Between the batch and the envs ---------------------------------------------------------------------------------

    def reset_team(self, team: int, seed: int | None = None, options: dict[str, Any] | None = None) -> np.ndarray:
        """Reset a team through its env (:meth:`FormationEnv.reset`), start its episode's sums, and load it.

        :return: the team's ``(n, dim)`` observations
        """
        observations, _ = self.envs[team].reset(seed=seed, options=options)
        self.episode_lengths[team] = self.episode_returns[team] = 0
        self.episode_errors[team] = self.episode_terms[team] = self.episode_collisions[team] = 0
        self.load(team)
        return np.stack(list(observations.values()))

    def load(self, team: int) -> None:
        """Take a team's state from its env (after a reset, or after anything that may have changed the env)."""
        env, rows = self.envs[team], self.team_rows(team)
        self._stale[team] = False
        self._coefficients[team] = env._coefficients
        self.live[team] = bool(env.agents)
        if env.world is None:
            return
        self.positions[rows] = env.world.positions
        self.velocities[rows] = env.world.velocities
        self.previous_actions[rows] = env.previous_actions
        self.previous_rewards[rows] = env.previous_rewards
        self.contacts[rows, 0], self.contacts[rows, 1] = env._contacts
        self.lidar[:, rows] = env._lidar
        self.goals[team] = env.goal
        circles, visible, channels = env.lidar.layout
        self._lidar_circles = _widened(self._lidar_circles, len(channels))
        self._lidar_visible = _widened(self._lidar_visible, len(channels))
        self._lidar_channels = _widened(self._lidar_channels, len(channels))
        self._lidar_circles[team, : len(channels)] = circles
        self._lidar_visible[rows, : len(channels)] = visible
        self._lidar_channels[team, : len(channels)] = channels
        self._lidar_counts[team] = len(channels)
        self.step_counts[team] = env.step_count
        self.goal_distances[team] = env.goal_distance
        self.previous_offsets[team] = env._previous_centroid_goal_offset
        formation = env.formation
        self.centroids[team] = formation.centroid
        self.centroid_distances[rows] = formation.centroid_distances
        self.neighbour_offsets[rows] = formation.neighbour_offsets
        self.neighbour_distances[rows] = formation.neighbour_distances
        self.bearings[rows] = formation.bearings
        self.angles[rows] = formation.angles_deg
        self.angle_errors[rows] = formation.angle_errors_deg
        self.bearing_errors[rows] = formation.bearing_errors
        self.orientation_flags[rows] = formation.orientation_flags
        self.range_flags[team] = formation.range_flag

    def sync(self, team: int) -> None:
        """Write a team's state into its env, so that its attributes, ``team_state()`` and ``render()`` are current."""
        if not self._stale[team]:
            return
        env, rows = self.envs[team], self.team_rows(team)
        self._stale[team] = False
        env.step_count = int(self.step_counts[team])
        env.goal_distance = float(self.goal_distances[team])
        env._previous_centroid_goal_offset = self.previous_offsets[team].copy()
        env.previous_actions = self.previous_actions[rows].copy()
        env.previous_rewards = self.previous_rewards[rows].copy()
        env._contacts = (self.contacts[rows, 0].tolist(), self.contacts[rows, 1].tolist())
        env.world.positions, env.world.velocities = self.positions[rows].copy(), self.velocities[rows].copy()
        env._lidar = (self.lidar[0, rows].copy(), self.lidar[1, rows].copy())
        env.formation = FormationState(
            centroid=self.centroids[team].copy(),
            centroid_distances=self.centroid_distances[rows].copy(),
            neighbour_offsets=self.neighbour_offsets[rows].copy(),
            neighbour_distances=self.neighbour_distances[rows].copy(),
            bearings=self.bearings[rows].copy(),
            angles_deg=self.angles[rows].copy(),
            angle_errors_deg=self.angle_errors[rows].copy(),
            bearing_errors=self.bearing_errors[rows].copy(),
            orientation_flags=self.orientation_flags[rows].copy(),
            range_flag=bool(self.range_flags[team]),
        )
        env.agents = list(env.possible_agents) if self.live[team] else []

    def episode_summary(self, team: int, success: bool) -> dict[str, Any]:
        """The team's episode summary so far (as :meth:`EpisodeStatistics.summary`)."""
        return episode_summary(
            int(self.episode_lengths[team]),
            float(self.episode_returns[team]),
            self.episode_errors[team].tolist(),
            self.episode_collisions[team].tolist(),
            self.episode_terms[team].tolist(),
            success,
            self.envs[team].stage,
        )

    # Stepping -------------------------------------------------------------------------------------------------------

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """Step every team under ``actions``; teams that end stay ended until :meth:`reset_team`.

        :param actions: ``(agents, 2)`` finite actions, clipped to [-1, 1], every team's agents one after the other
        :return: observations ``(agents, dim)`` float32, rewards ``(agents,)``, terminated and truncated ``(teams,)``,
            as :meth:`FormationEnv.step_array` gives them team by team, and the agents' info values (see :meth:`infos`)
        """
        if not self.live.all():
            raise RuntimeError(f"step() on ended teams {np.flatnonzero(~self.live).tolist()}; reset them first")
        config, starts = self.config, self.starts
        self._stale[:] = True
        previous_velocities = self.velocities
        previous_goal_distances = self.goal_distances
        commanded = clamp_speed(self.velocities + (actions * config.force_max) * (config.dt / config.agent_mass), config.v_max)
        worlds = [env.world for env in self.envs]
        moved = [world.advance(commanded[starts[team] : starts[team + 1]]) for team, world in enumerate(worlds)]
        # the worlds' positions and velocities are written back in sync()
        self.positions, self.velocities = split_state(np.concatenate([world.agent_states for world in worlds]), config.v_max)
        # (agents, obstacles or walls) touched by each agent in the step
        self.contacts = contacts = np.zeros((len(actions), 2), dtype=np.int64)
        for team, touched in enumerate(moved):
            if touched is not None:
                contacts[starts[team] : starts[team + 1]] = np.transpose(touched)
        self.step_counts += 1
        np.subtract(self.goals, self.centroids, out=self.previous_offsets)
        nearest_agent, nearest_obstacle = _measure_teams(
            self.positions,
            starts,
            self._neighbours,
            self._reference,
            self._beta_ref,
            config.d_ref,
            config.agent_radius,
            self._lidar_circles,
            self._lidar_counts,
            config.world_width,
            config.world_height,
            self.centroids,
            self.centroid_distances,
            self.neighbour_offsets,
            self.neighbour_distances,
            self.bearings,
            self.angles,
            self.angle_errors,
            self.bearing_errors,
            self.orientation_flags,
            self.range_flags,
        )
        offsets = (self.goals - self.centroids).tolist()
        self.goal_distances = np.array([math.hypot(x, y) for x, y in offsets])  # as FormationEnv: Python's hypot
        terms = _team_terms(
            starts,
            self.step_counts,
            self.angle_errors,
            self.bearing_errors,
            self.neighbour_distances,
            self.centroid_distances,
            previous_goal_distances,
            self.goal_distances,
            previous_velocities,
            self.velocities,
            self._neighbours,
            nearest_agent,
            nearest_obstacle,
            self._reward_constants,
            config.max_steps,
            config.team_reward,
        )
        rewards, team_means = self._combine(terms)
        success = self.goal_distances <= config.eta_g
        truncated = ~success & (self.step_counts >= config.max_steps)
        self.live = ~(success | truncated)
        self.previous_actions = actions.copy()  # the batch's own: resets overwrite rows of it in place
        self.previous_rewards = rewards.copy()
        observations = np.empty((len(actions), self.observation_dim), dtype=np.float32)
        info_values = _observe_teams(
            observations,
            self.lidar,
            starts,
            self.positions,
            self.velocities,
            self.goals,
            self.centroids,
            self.previous_offsets,
            self.neighbour_offsets,
            self.neighbour_distances,
            self.centroid_distances,
            self.angle_errors,
            self.bearing_errors,
            self.orientation_flags,
            self.range_flags,
            self._neighbours,
            self._reference,
            config.observe_reference_bearings,
            self._directions,
            self._lidar_circles,
            self._lidar_visible,
            self._lidar_channels,
            self._lidar_counts,
            config.agent_radius,
            config.world_width,
            config.world_height,
            config.lidar_range,
            config.d_ref,
            config.eta_c,
            self.step_counts,
            actions,
            rewards,
            self.goal_distances,
            terms,
            contacts,
            team_means,
            self.episode_lengths,
            self.episode_returns,
            self.episode_errors,
            self.episode_collisions,
            self.episode_terms,
        )
        return observations, rewards, success, truncated, info_values

    def _combine(self, terms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eqs 26 / 32 / 42 for every agent, and every team's mean reward, with numpy's own sums of one team at a time.

        :param terms: every team's ``(terms, n)`` block, one after the other, flat
        :return: rewards ``(agents,)`` and team means ``(teams,)``
        """
        clip = self.config.reward_clip
        if self._single_size:  # one reshape: each team's block is the (terms, n) matrix FormationEnv multiplies
            n_agents = int(self.starts[1])
            sums = (self._coefficients[:, None, :] @ terms.reshape(self.n_teams, _N_TERMS, n_agents))[:, 0, :]
            rewards = np.minimum(np.maximum(sums, -clip), clip)
            return rewards.reshape(-1), rewards.mean(axis=1)
        rewards, team_means = np.empty(int(self.starts[-1])), np.empty(self.n_teams)
        for n_agents, (teams, rows) in self._groups.items():
            blocks = np.stack([terms[_N_TERMS * self.starts[t] : _N_TERMS * self.starts[t + 1]] for t in teams])
            sums = (self._coefficients[teams, None, :] @ blocks.reshape(len(teams), _N_TERMS, n_agents))[:, 0, :]
            group = np.minimum(np.maximum(sums, -clip), clip)
            rewards[rows], team_means[teams] = group.reshape(-1), group.mean(axis=1)
        return rewards, team_means

    def infos(self, values: np.ndarray, terminated: np.ndarray) -> list[dict[str, Any]]:
        """Every agent's info dict after :meth:`step` (as :meth:`FormationEnv.step_array` gives them).

        :param values: the info values :meth:`step` returned
        :param terminated: the teams' success, as :meth:`step` returned it
        """
        return agent_infos(values, self.contacts, np.repeat(terminated, self.sizes))


def _widened(array: np.ndarray, size: int) -> np.ndarray:
    """``array``, or a copy with its second axis grown to ``size`` (the new entries zero)."""
    if array.shape[1] >= size:
        return array
    grown = np.zeros((array.shape[0], size, *array.shape[2:]), dtype=array.dtype)
    grown[:, : array.shape[1]] = array
    return grown


# Compiled kernels: each loops over the teams and calls, for each, the very kernels FormationEnv calls for one team ----


@numba.njit(cache=True)
def _measure_teams(
    positions: np.ndarray,
    starts: np.ndarray,
    neighbours: np.ndarray,
    reference: np.ndarray,
    beta_ref: np.ndarray,
    d_ref: float,
    agent_radius: float,
    circles: np.ndarray,
    circle_counts: np.ndarray,
    width: float,
    height: float,
    centroids: np.ndarray,
    centroid_distances: np.ndarray,
    neighbour_offsets: np.ndarray,
    neighbour_distances: np.ndarray,
    bearings: np.ndarray,
    angles: np.ndarray,
    angle_errors: np.ndarray,
    bearing_errors: np.ndarray,
    orientation_flags: np.ndarray,
    range_flags: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``measure_formation`` and ``nearest_gaps`` of every team, into the given arrays; returns the nearest gaps."""
    n_slots = positions.shape[0]
    nearest_agent, nearest_obstacle = np.empty(n_slots), np.empty(n_slots)
    for team in range(starts.shape[0] - 1):
        start, end = starts[team], starts[team + 1]
        team_positions = positions[start:end]
        centroid, distances, offsets, neighbour_distance, bearing, angle, bearing_error = _measure(
            team_positions, neighbours[start:end], reference[start:end]
        )
        centroids[team] = centroid
        centroid_distances[start:end] = distances
        neighbour_offsets[start:end] = offsets
        neighbour_distances[start:end] = neighbour_distance
        bearings[start:end] = bearing
        angles[start:end] = angle
        bearing_errors[start:end] = bearing_error
        in_range = True
        for agent in range(end - start):
            angle_errors[start + agent] = beta_ref[team] - angle[agent]
            orientation_flags[start + agent] = angle[agent] > 0.0 and angle[agent] < 180.0
            for slot in range(neighbour_distance.shape[1]):
                in_range = in_range and neighbour_distance[agent, slot] <= d_ref
        range_flags[team] = in_range
        obstacles = circles[team, : circle_counts[team] - (end - start)]  # the lidar's circles: obstacles, then agents
        agent_gap, obstacle_gap = nearest_gaps(team_positions, agent_radius, obstacles, width, height)
        nearest_agent[start:end] = agent_gap
        nearest_obstacle[start:end] = obstacle_gap
    return nearest_agent, nearest_obstacle


@numba.njit(cache=True)
def _team_terms(
    starts: np.ndarray,
    step_counts: np.ndarray,
    angle_errors: np.ndarray,
    bearing_errors: np.ndarray,
    neighbour_distances: np.ndarray,
    centroid_distances: np.ndarray,
    previous_goal_distances: np.ndarray,
    goal_distances: np.ndarray,
    previous_velocities: np.ndarray,
    velocities: np.ndarray,
    neighbours: np.ndarray,
    nearest_agent: np.ndarray,
    nearest_obstacle: np.ndarray,
    constants: np.ndarray,
    max_steps: int,
    team_reward: bool,
) -> np.ndarray:  # pragma: no cover - compiled
    """Every team's reward terms: its ``(terms, n)`` block of ``reward_terms``, the blocks one after the other, flat."""
    n_terms = _N_TERMS
    terms = np.empty(n_terms * velocities.shape[0])
    for team in range(starts.shape[0] - 1):
        start, end = starts[team], starts[team + 1]
        block = _reward_terms(
            step_counts[team],
            angle_errors[start:end],
            bearing_errors[start:end],
            neighbour_distances[start:end],
            centroid_distances[start:end],
            previous_goal_distances[team],
            goal_distances[team],
            previous_velocities[start:end],
            velocities[start:end],
            neighbours[start:end],
            nearest_agent[start:end],
            nearest_obstacle[start:end],
            constants[team],
            max_steps,
            team_reward,
        )
        terms[n_terms * start : n_terms * end] = block.ravel()
    return terms


@numba.njit(cache=True)
def _observe_teams(
    out: np.ndarray,
    lidar: np.ndarray,
    starts: np.ndarray,
    positions: np.ndarray,
    velocities: np.ndarray,
    goals: np.ndarray,
    centroids: np.ndarray,
    previous_offsets: np.ndarray,
    neighbour_offsets: np.ndarray,
    neighbour_distances: np.ndarray,
    centroid_distances: np.ndarray,
    angle_errors: np.ndarray,
    bearing_errors: np.ndarray,
    orientation_flags: np.ndarray,
    range_flags: np.ndarray,
    neighbours: np.ndarray,
    reference: np.ndarray,
    observe_reference: bool,
    directions: np.ndarray,
    lidar_circles: np.ndarray,
    lidar_visible: np.ndarray,
    lidar_channels: np.ndarray,
    lidar_counts: np.ndarray,
    agent_radius: float,
    width: float,
    height: float,
    lidar_range: float,
    d_ref: float,
    eta_c: float,
    step_counts: np.ndarray,
    actions: np.ndarray,
    rewards: np.ndarray,
    goal_distances: np.ndarray,
    terms: np.ndarray,
    contacts: np.ndarray,
    team_means: np.ndarray,
    episode_lengths: np.ndarray,
    episode_returns: np.ndarray,
    episode_errors: np.ndarray,
    episode_collisions: np.ndarray,
    episode_terms: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """Every team's lidar scan and observations (into ``lidar`` and ``out``), its agents' info values, and its
    episode's running sums; returns the info values, ``(agents, 5 + terms)``: the five errors and distances of
    ``INFO_KEYS`` and the reward terms."""
    n_terms = _N_TERMS
    values = np.empty((positions.shape[0], 5 + n_terms))
    dim = out.shape[1]
    for team in range(starts.shape[0] - 1):
        start, end = starts[team], starts[team + 1]
        n_agents, n_circles = end - start, lidar_counts[team]
        # the team's Lidar.scan: the agents' circles (the last ones) take the agents' positions
        circles = lidar_circles[team, :n_circles]
        circles[n_circles - n_agents :, :2] = positions[start:end]
        ranges = lidar_ranges(
            positions[start:end],
            agent_radius,
            directions,
            circles,
            lidar_visible[start:end, :n_circles],
            lidar_channels[team, :n_circles],
            width,
            height,
            lidar_range,
        )
        ranges /= lidar_range
        lidar[:, start:end] = ranges
        _fill_observations(
            out[start:end],
            lidar[0, start:end],
            lidar[1, start:end],
            positions[start:end],
            velocities[start:end],
            goals[team],
            centroids[team],
            previous_offsets[team],
            neighbour_offsets[start:end],
            neighbour_distances[start:end],
            centroid_distances[start:end],
            angle_errors[start:end],
            orientation_flags[start:end],
            range_flags[team],
            neighbours[start:end],
            d_ref,
            eta_c,
            step_counts[team],
            actions[start:end],
            rewards[start:end],
        )
        if observe_reference:
            for agent in range(n_agents):
                for k in range(4):
                    out[start + agent, dim - 4 + k] = reference[start + agent, k // 2, k % 2]
        # info values and the episode's running sums (EpisodeStatistics.add: agent by agent, each over n)
        episode_lengths[team] += 1
        episode_returns[team] += team_means[team]
        angle, bearing, distance = agent_errors(
            angle_errors[start:end], bearing_errors[start:end], neighbour_distances[start:end], d_ref
        )
        for agent in range(n_agents):
            row = start + agent
            values[row, 0] = angle[agent]
            values[row, 1] = bearing[agent]
            values[row, 2] = distance[agent]
            values[row, 3] = centroid_distances[row]
            values[row, 4] = goal_distances[team]
            episode_errors[team, 0] += angle[agent] / n_agents
            episode_errors[team, 1] += bearing[agent] / n_agents
            episode_errors[team, 2] += distance[agent] / n_agents
            episode_collisions[team, 0] += contacts[row, 1]
            episode_collisions[team, 1] += contacts[row, 0]
            for term in range(n_terms):
                value = terms[n_terms * start + term * n_agents + agent]
                values[row, 5 + term] = value
                episode_terms[team, term] += value / n_agents
    return values
