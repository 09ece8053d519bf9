"""``FormationEngine``: the one implementation of a reset, a step and a team's episode state, for any number of teams.

Every view of the task steps through it: :class:`~sb3_formation.env.formation_env.FormationEnv` is the PettingZoo
view of an engine of one team, :class:`~sb3_formation.env.blocks.EngineBlock` adds automatic resets and episode
records for the SB3 ``VecEnv`` and for evaluation. The engine never resets a team by itself: a team whose episode
ended is left as it ended (its last observation is the terminal one) and is not stepped until it is reset.

A step of the live teams is: one compiled call for the forces, Pymunk for each team (each team has its own space, so
that a team's numbers never depend on the others), then three compiled calls over the stacked arrays of every agent
(formation geometry and nearest gaps; reward terms; lidar, observations, info values and the episode's running sums),
with numpy between them for the weighted sum of the reward terms and the team means, and Python's ``math.hypot`` for
the goal distance. A reset measures the new team with the same kernels. ``docs/design.md`` follows one step through.

Arrays that the engine returns are never written again: the next step makes new ones, and a reset copies an array
before it writes the reset team's rows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple, cast

import numba
import numpy as np
from gymnasium.utils import seeding

from sb3_formation.env.clearance import ClearanceMap, goal_field, path_distance
from sb3_formation.env.config import INFO_KEYS, REWARD_TERMS, FormationConfig
from sb3_formation.env.episodes import episode_summary
from sb3_formation.env.geometry import FormationState, _measure, agent_errors, reference_bearings, ring_neighbours
from sb3_formation.env.observations import _fill_observations, observation_fields, observation_layout
from sb3_formation.env.rewards import _reward_terms, combine_rewards, goal_term, nearest_gaps, reward_constants
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.scenes import check_scenes_fit, draw_scenario
from sb3_formation.env.sensors import Lidar, lidar_ranges
from sb3_formation.env.state import TeamState
from sb3_formation.env.world import World, clamp_speed, split_state

_N_TERMS = len(REWARD_TERMS)
_GOAL = REWARD_TERMS.index("goal")  # the goal term's row of a team's (terms, n) block
#: columns of the info values of a step: the five errors and distances of :data:`INFO_KEYS`, then the reward terms
#: (:func:`agent_infos` adds the contacts and success)
INFO_VALUES = 5 + _N_TERMS


class EngineStep(NamedTuple):
    """What a step of a :class:`FormationEngine` gives, for every agent (rows) or team; rows of teams that were not
    stepped hold what they held before the step (rewards: 0)."""

    observations: np.ndarray  #: ``(agents, dim)`` float32
    rewards: np.ndarray  #: ``(agents,)``
    terminated: np.ndarray  #: ``(teams,)``: the centroid reached the goal in this step
    truncated: np.ndarray  #: ``(teams,)``: the step limit T_s ended the episode
    info_values: np.ndarray  #: ``(agents, INFO_VALUES)``
    contacts: np.ndarray  #: ``(agents, 2)`` other agents, then obstacles or walls, touched in the step
    positions: np.ndarray  #: ``(agents, 2)`` (m)
    velocities: np.ndarray  #: ``(agents, 2)`` (m/s)


class FormationEngine:
    """Teams of one task (they may differ in ``n_agents`` only), reset one by one and stepped together.

    Agents are stacked one team after the other (team t holds rows ``starts[t]:starts[t + 1]``, agent 0 first). Each
    team has its own scenario generator, curriculum stage, Pymunk world and lidar.

    :param configs: the task configuration of each team
    """

    def __init__(self, configs: Sequence[FormationConfig]) -> None:
        self.configs = list(configs)
        if not self.configs:
            raise ValueError("a FormationEngine needs at least one team")
        config = self.config = self.configs[0]
        for team_config in self.configs:
            if team_config.replace(n_agents=config.n_agents) != config:
                raise ValueError("the teams of a FormationEngine must share one task (they may differ in n_agents only)")
        for team_config in {team_config.n_agents: team_config for team_config in self.configs}.values():
            check_scenes_fit(team_config)
        #: team sizes, and the first row of each team (and the number of rows, last)
        self.sizes = sizes = np.array([team_config.n_agents for team_config in self.configs])
        self.starts = np.concatenate([[0], np.cumsum(sizes)])
        n_teams, n_slots = len(sizes), int(self.starts[-1])
        #: the fields of an agent's observation (Table 3.1), in order
        self.observation_fields = observation_fields(config)
        self.observation_dim = dim = sum(field.size for field in self.observation_fields)
        #: team size -> (teams of that size, their agents' rows in team order): the groups of the stacked numpy work
        self._groups = {
            int(size): (teams, np.concatenate([np.arange(self.starts[t], self.starts[t + 1]) for t in teams]))
            for size in np.unique(sizes)
            for teams in [np.flatnonzero(sizes == size)]
        }
        self._single_size = len(self._groups) == 1
        # per-agent constants, stacked: neighbours (indices within the team) and reference bearings
        self.neighbours = np.concatenate([ring_neighbours(int(n)) for n in sizes]).astype(np.int64)
        self.reference_bearings = np.ascontiguousarray(np.concatenate([reference_bearings(int(n)) for n in sizes]))
        # per-team objects and constants
        self.lidars = [
            Lidar(c.lidar_rays, c.lidar_range, c.agent_radius, c.world_width, c.world_height, ring_neighbours(c.n_agents))
            for c in self.configs
        ]
        self._directions = self.lidars[0].directions
        self._reward_constants = np.stack([reward_constants(team_config) for team_config in self.configs])
        self._beta_ref = np.array([team_config.beta_ref_deg for team_config in self.configs])
        self.worlds: list[World | None] = [None] * n_teams
        self.scenarios: list[Scenario | None] = [None] * n_teams
        self.generators: list[np.random.Generator] = []
        self.generator_seeds: list[int] = []
        for _ in range(n_teams):
            generator, seed = seeding.np_random()
            self.generators.append(generator)
            self.generator_seeds.append(seed)
        self.stages = np.zeros(n_teams, dtype=np.int64)
        self._coefficients = np.zeros((n_teams, _N_TERMS))
        for team, team_config in enumerate(self.configs):
            self.set_stage(team, team_config.stage)
        # the episode state of every agent and team
        self.observations = np.zeros((n_slots, dim), dtype=np.float32)
        self.info_values = np.zeros((n_slots, INFO_VALUES))
        self.positions = np.zeros((n_slots, 2))
        self.velocities = np.zeros((n_slots, 2))
        # unicycles' headings (rad) and forward speeds (m/s), and the heading's columns of an observation (cos, sin)
        self.headings, self.forward_speeds = np.zeros(n_slots), np.zeros(n_slots)
        self.unicycle = config.dynamics == "unicycle"
        if self.unicycle:
            self._heading_column = observation_layout(self.observation_fields)["heading"].start
        self.previous_actions = np.zeros((n_slots, 2))
        self.previous_rewards = np.zeros(n_slots)
        self.contacts = np.zeros((n_slots, 2), dtype=np.int64)  # agents, obstacles touched in the last step
        self.lidar = np.zeros((2, n_slots, config.lidar_rays))
        self.goals = np.zeros((n_teams, 2))
        # every team's lidar layout (Lidar.layout: its obstacles then its agents as circles, who sees which, channels),
        # padded to the widest team's; the obstacles' circles are also what the rewards' nearest gaps measure
        self._lidar_circles = np.zeros((n_teams, 0, 3))
        self._lidar_visible = np.zeros((n_slots, 0), dtype=bool)
        self._lidar_channels = np.zeros((n_teams, 0), dtype=np.int64)
        self._lidar_counts = np.zeros(n_teams, dtype=np.int64)
        self._walls = np.zeros((n_teams, 0, 5))  # every team's walls, padded to the most walls of a team
        self._wall_counts = np.zeros(n_teams, dtype=np.int64)
        self.step_counts = np.zeros(n_teams, dtype=np.int64)
        self.goal_distances = np.zeros(n_teams)
        #: the way (m) to the goal whose decrease the goal term rewards: the goal distance, or with ``goal_progress:
        #: geodesic`` the way round the shapes on the team's goal field (computed at its reset)
        self.ways = np.zeros(n_teams)
        self._goal_fields: list[tuple[ClearanceMap, np.ndarray] | None] = [None] * n_teams
        self._geodesic = any(team_config.goal_progress == "geodesic" for team_config in self.configs)
        self.previous_offsets = np.zeros((n_teams, 2))  # c_g^v one step earlier
        #: teams in an episode (reset and not ended since)
        self.live = np.zeros(n_teams, dtype=bool)
        self._every_team, self._every_team_list = np.arange(n_teams), list(range(n_teams))
        #: teams whose centroid reached the goal in their last step
        self.success = np.zeros(n_teams, dtype=bool)
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
        # running sums of every team's episode (see episode_summary)
        self.episode_lengths = np.zeros(n_teams, dtype=np.int64)
        self.episode_returns = np.zeros(n_teams)
        self.episode_errors = np.zeros((n_teams, 3))
        self.episode_collisions = np.zeros((n_teams, 2), dtype=np.int64)
        self.episode_terms = np.zeros((n_teams, _N_TERMS))
        self.episode_comm_exceeded = np.zeros(n_teams, dtype=np.int64)  # steps with a neighbour beyond d_comm

    @property
    def n_teams(self) -> int:
        return len(self.configs)

    def team_rows(self, team: int) -> slice:
        """The rows of a team's agents, agent 0 first."""
        return slice(int(self.starts[team]), int(self.starts[team + 1]))

    def set_stage(self, team: int, stage: int) -> None:
        """Switch a team's curriculum stage (1, 2 or 3): rewards change at once, placements at its next reset."""
        coefficients = self.configs[team].reward_coefficients(stage)  # validates the stage
        self.stages[team] = int(stage)
        self._coefficients[team] = [coefficients[name] for name in REWARD_TERMS]

    def seed(self, team: int, seed: int | None) -> None:
        """Give a team a new scenario generator, seeded with ``seed`` (``None``: from the operating system)."""
        self.generators[team], self.generator_seeds[team] = seeding.np_random(seed)

    # Reset --------------------------------------------------------------------------------------------------------

    def reset(self, team: int, seed: int | None = None, scenario: Scenario | None = None) -> np.ndarray:
        """Start a team's next episode: draw its scenario of the team's stage (or place ``scenario``) and measure it.

        :param team: the team
        :param seed: re-seed the team's generator first (see :meth:`seed`)
        :param scenario: place this instead of drawing one (validated against the team's task)
        :return: the team's ``(n, dim)`` observations (a copy)
        """
        config = self.configs[team]
        if seed is not None:
            self.seed(team, seed)
        if scenario is None:
            scenario = draw_scenario(config, int(self.stages[team]), self.generators[team])
        elif not isinstance(scenario, Scenario):
            raise TypeError(f"the scenario must be a Scenario, got {type(scenario).__name__}")
        else:
            scenario.validate(config)
        world = self.worlds[team]
        if world is None:
            world = self.worlds[team] = World(config, scenario)
        else:
            world.place(scenario)
        self.scenarios[team] = scenario
        lidar = self.lidars[team]
        lidar.set_obstacles(scenario.obstacles, scenario.walls)
        self._load_lidar_layout(team, lidar)
        rows = self.team_rows(team)
        # arrays that were returned are copied before their rows change (see the module docstring)
        for name in ("observations", "info_values", "contacts", "positions", "velocities"):
            setattr(self, name, getattr(self, name).copy())
        self.positions[rows] = world.positions
        self.velocities[rows] = world.velocities
        if self.unicycle:
            self.headings, self.forward_speeds = self.headings.copy(), self.forward_speeds.copy()
            self.headings[rows], self.forward_speeds[rows] = world.headings, 0.0
        self.previous_actions[rows] = 0.0
        self.previous_rewards[rows] = 0.0
        self.contacts[rows] = 0
        self.goals[team] = scenario.goal
        self.step_counts[team] = 0
        self.live[team], self.success[team] = True, False
        self.episode_lengths[team] = self.episode_returns[team] = self.episode_comm_exceeded[team] = 0
        self.episode_errors[team] = self.episode_terms[team] = self.episode_collisions[team] = 0
        active = np.array([team])
        self._measure(active)
        self.goal_distances[team] = math.hypot(*(self.goals[team] - self.centroids[team]).tolist())
        if config.goal_progress == "geodesic":
            clearance = ClearanceMap.of(config, cast(np.ndarray, scenario.obstacles), cast(np.ndarray, scenario.walls))
            self._goal_fields[team] = clearance, goal_field(clearance, scenario.goal)
        self.ways[team] = self._way(team)
        self.previous_offsets[team] = self.goals[team] - self.centroids[team]
        no_terms = np.zeros(_N_TERMS * len(self.previous_rewards))
        self._observe(active, self.observations, self.info_values, no_terms, np.zeros(self.n_teams), accumulate=False)
        observations: np.ndarray = self.observations[rows].copy()
        return observations

    def _way(self, team: int) -> float:
        """The team's way (m) to its goal now (:attr:`ways`)."""
        field = self._goal_fields[team]
        if self.configs[team].goal_progress == "euclidean" or field is None:
            return float(self.goal_distances[team])
        return path_distance(*field, self.centroids[team])

    def _load_lidar_layout(self, team: int, lidar: Lidar) -> None:
        circles, visible, channels = lidar.layout
        count, rows = len(channels), self.team_rows(team)
        self._lidar_circles = _widened(self._lidar_circles, count)
        self._lidar_visible = _widened(self._lidar_visible, count)
        self._lidar_channels = _widened(self._lidar_channels, count)
        self._lidar_circles[team, :count] = circles
        self._lidar_visible[rows, :count] = visible
        self._lidar_channels[team, :count] = channels
        self._lidar_counts[team] = count
        self._walls = _widened(self._walls, len(lidar.walls))
        self._walls[team, : len(lidar.walls)] = lidar.walls
        self._wall_counts[team] = len(lidar.walls)

    # Step ---------------------------------------------------------------------------------------------------------

    def step(self, actions: np.ndarray) -> EngineStep:
        """Step every live team under its agents' rows of ``actions``; teams that end stay ended until reset.

        :param actions: ``(agents, 2)`` finite actions within [-1, 1] (the views check and clip them), every team's
            agents one after the other; the rows of teams that are not live are ignored
        """
        everyone = bool(self.live.all())
        pick: slice | np.ndarray
        if everyone:  # as in every VecEnv step: no team to leave out
            active, teams, pick, stepped = self._every_team, self._every_team_list, slice(None), None
        else:
            active = np.flatnonzero(self.live)
            if active.size == 0:  # nothing to step (a block of an evaluation whose episodes are all played)
                unchanged = (self.info_values, self.contacts, self.positions, self.velocities)
                ended = np.zeros(self.n_teams, dtype=bool)
                return EngineStep(self.observations, np.zeros(len(actions)), ended, ended.copy(), *unchanged)
            teams, pick = active.tolist(), active
            stepped = np.repeat(self.live, self.sizes)  # the rows of the live teams
        config, starts = self.config, self.starts
        previous_velocities = self.velocities
        worlds = cast("list[World]", self.worlds)  # a live team has been reset, so has a world
        pushes = (actions * config.force_max) * (config.dt / config.agent_mass)  # velocity changes (m/s)
        if self.unicycle:  # the forward force along the heading, the turn action a share of the turn-rate limit
            forward = np.clip(self.forward_speeds + pushes[:, 0], -config.v_max, config.v_max)
            turns = actions[:, 1] * config.max_turn_rate
            moved = [
                (team, worlds[team].drive(forward[starts[team] : starts[team + 1]], turns[starts[team] : starts[team + 1]]))
                for team in teams
            ]
            positions = np.concatenate([worlds[team].agent_states[:, :2] for team in teams])
            headings = np.concatenate([worlds[team].headings for team in teams])
            speeds = np.concatenate([worlds[team].forward_speeds for team in teams])
            velocities = speeds[:, None] * np.stack([np.cos(headings), np.sin(headings)], axis=1)
            self.headings = self._new_rows(self.headings, headings, stepped)
            self.forward_speeds = self._new_rows(self.forward_speeds, speeds, stepped)
        else:
            commanded = clamp_speed(self.velocities + pushes, config.v_max)
            moved = [(team, worlds[team].advance(commanded[starts[team] : starts[team + 1]])) for team in teams]
            positions, velocities = split_state(np.concatenate([worlds[team].agent_states for team in teams]), config.v_max)
        self.positions = self._new_rows(self.positions, positions, stepped)
        self.velocities = self._new_rows(self.velocities, velocities, stepped)
        contacts = np.zeros((len(actions), 2), dtype=np.int64) if everyone else self.contacts.copy()
        if stepped is not None:
            contacts[stepped] = 0
        for team, touched in moved:
            if touched is not None:
                contacts[starts[team] : starts[team + 1]] = np.transpose(touched)
        self.contacts = contacts
        self.step_counts[pick] += 1
        self.previous_offsets[pick] = self.goals[pick] - self.centroids[pick]
        nearest_agent, nearest_obstacle = self._measure(active)  # rows of other teams: undefined
        previous_goal_distances = self.goal_distances
        self.goal_distances = goal_distances = self.goal_distances.copy()
        for team, (x, y) in zip(teams, (self.goals[pick] - self.centroids[pick]).tolist()):
            goal_distances[team] = math.hypot(x, y)  # Python's hypot: numba's and numpy's round otherwise
        previous_ways = self.ways
        if self._geodesic:
            self.ways = self.ways.copy()
            for team in teams:
                self.ways[team] = self._way(team)
        else:  # the thesis's goal term: the way is the goal distance
            self.ways = goal_distances
        terms = np.empty(_N_TERMS * len(actions)) if everyone else np.zeros(_N_TERMS * len(actions))
        _team_terms(
            terms,
            active,
            starts,
            self.step_counts,
            self.angle_errors,
            self.bearing_errors,
            self.neighbour_distances,
            self.centroid_distances,
            previous_ways,
            self.ways,
            goal_distances,
            previous_velocities,
            self.velocities,
            self.neighbours,
            nearest_agent,
            nearest_obstacle,
            self._reward_constants,
            config.max_steps,
            config.team_reward,
        )
        rewards, team_means = self._combine(terms)
        terminated = goal_distances <= config.eta_g
        truncated = ~terminated & (self.step_counts >= config.max_steps)
        if not everyone:  # teams that were not stepped did not end now
            terminated &= self.live
            truncated &= self.live
        self.success[pick] = terminated[pick]
        self.live = self.live & ~(terminated | truncated)
        self.previous_actions = self._new_rows(self.previous_actions, actions, stepped, select=True)
        observed = rewards
        if self._geodesic:  # an agent observes the reward of the thesis's goal term: the map stays out of observations
            straight = terms.copy()
            for team in teams:
                team_config = self.configs[team]
                block = straight[_N_TERMS * starts[team] : _N_TERMS * starts[team + 1]].reshape(_N_TERMS, -1)
                block[_GOAL] = goal_term(
                    previous_goal_distances[team],
                    goal_distances[team],
                    goal_distances[team],
                    team_config.eta_g,
                    team_config.r_reached,
                    team_config.k1,
                    team_config.dt,
                    team_config.v_max,
                )
            observed = self._combine(straight)[0]
        self.previous_rewards = self._new_rows(self.previous_rewards, observed, stepped, select=True)
        observations = np.empty_like(self.observations) if everyone else self.observations.copy()
        info_values = np.empty_like(self.info_values) if everyone else self.info_values.copy()
        self._observe(active, observations, info_values, terms, team_means, accumulate=True)
        self.observations, self.info_values = observations, info_values
        return EngineStep(observations, rewards, terminated, truncated, info_values, contacts, self.positions, self.velocities)

    @staticmethod
    def _new_rows(old: np.ndarray, new: np.ndarray, rows: np.ndarray | None, select: bool = False) -> np.ndarray:
        """A new array: ``new`` where ``rows`` (every row when ``None``), ``old`` elsewhere.

        :param select: ``new`` has a row for every agent (else only for ``rows``)
        """
        if rows is None:
            return new.copy() if select else new
        merged: np.ndarray = old.copy()
        merged[rows] = new[rows] if select else new
        return merged

    def _measure(self, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measure the formation of the ``active`` teams (into the formation arrays); return the nearest gaps."""
        config = self.config
        return _measure_teams(
            active,
            self.positions,
            self.starts,
            self.neighbours,
            self.reference_bearings,
            self._beta_ref,
            config.d_ref,
            config.agent_radius,
            self._lidar_circles,
            self._lidar_counts,
            self._walls,
            self._wall_counts,
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

    def _observe(
        self,
        active: np.ndarray,
        observations: np.ndarray,
        info_values: np.ndarray,
        terms: np.ndarray,
        team_means: np.ndarray,
        accumulate: bool,
    ) -> None:
        """Scan, observe and fill the info values of the ``active`` teams; with ``accumulate``, add the step to their
        episodes' running sums."""
        config = self.config
        _observe_teams(
            active,
            observations,
            info_values,
            self.lidar,
            self.starts,
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
            self.neighbours,
            self.reference_bearings,
            config.observe_reference_bearings,
            self._directions,
            self._lidar_circles,
            self._lidar_visible,
            self._lidar_channels,
            self._lidar_counts,
            self._walls,
            self._wall_counts,
            config.agent_radius,
            config.world_width,
            config.world_height,
            config.lidar_range,
            config.d_ref,
            config.d_comm,
            config.eta_c,
            self.step_counts,
            self.previous_actions,
            self.previous_rewards,
            self.goal_distances,
            terms,
            self.contacts,
            team_means,
            accumulate,
            self.episode_lengths,
            self.episode_returns,
            self.episode_errors,
            self.episode_collisions,
            self.episode_terms,
            self.episode_comm_exceeded,
        )
        if self.unicycle:  # the heading's cosine and sine (observation_fields)
            rows: slice | np.ndarray = slice(None)
            if len(active) < self.n_teams:
                rows = np.concatenate([np.arange(self.starts[team], self.starts[team + 1]) for team in active])
            column = self._heading_column
            observations[rows, column] = np.cos(self.headings[rows])
            observations[rows, column + 1] = np.sin(self.headings[rows])

    def _combine(self, terms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every agent's reward (:func:`~sb3_formation.env.rewards.combine_rewards`, the teams of one size at once)
        and every team's mean reward.

        :param terms: every team's ``(terms, n)`` block, one after the other, flat
        :return: rewards ``(agents,)`` and team means ``(teams,)``
        """
        clip = self.config.reward_clip
        if self._single_size:  # one reshape: each team's block is its (terms, n) matrix
            rewards = combine_rewards(terms.reshape(self.n_teams, _N_TERMS, -1), self._coefficients, clip)
            return rewards.reshape(-1), _row_means(rewards)
        rewards, team_means = np.empty(int(self.starts[-1])), np.empty(self.n_teams)
        for n_agents, (teams, rows) in self._groups.items():
            blocks = np.stack([terms[_N_TERMS * self.starts[t] : _N_TERMS * self.starts[t + 1]] for t in teams])
            group = combine_rewards(blocks.reshape(len(teams), _N_TERMS, n_agents), self._coefficients[teams], clip)
            rewards[rows], team_means[teams] = group.reshape(-1), _row_means(group)
        return rewards, team_means

    # Reading a team ------------------------------------------------------------------------------------------------

    def formation(self, team: int) -> FormationState:
        """A team's formation now (copies)."""
        rows = self.team_rows(team)
        return FormationState(
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

    def team_state(self, team: int) -> TeamState:
        """A frozen snapshot of a team now (after its last reset or step)."""
        if self.worlds[team] is None:
            raise RuntimeError(f"team {team} has not been reset")
        rows = self.team_rows(team)
        values = self.info_values[rows]
        scenario = cast(Scenario, self.scenarios[team])  # placed with the team's world
        return TeamState(
            step=int(self.step_counts[team]),
            positions=self.positions[rows],
            velocities=self.velocities[rows],
            goal=self.goals[team],
            obstacles=cast(np.ndarray, scenario.obstacles),  # arrays once the scenario is built
            walls=cast(np.ndarray, scenario.walls),
            neighbours=self.neighbours[rows],
            contacts_agent=self.contacts[rows, 0],
            contacts_obstacle=self.contacts[rows, 1],
            angle_errors_deg=values[:, 0],
            bearing_errors=values[:, 1],
            neighbour_distance_errors=values[:, 2],
            centroid=self.centroids[team],
            goal_distance=float(self.goal_distances[team]),
            lidar_obstacles=self.lidar[0, rows],
            lidar_agents=self.lidar[1, rows],
            headings=self.headings[rows] if self.unicycle else None,
        )

    def infos(self, team: int) -> list[dict[str, Any]]:
        """A team's agents' info dicts after its last reset or step (keys: :data:`INFO_KEYS`)."""
        rows = self.team_rows(team)
        success = np.full(rows.stop - rows.start, self.success[team])
        return agent_infos(self.info_values[rows], self.contacts[rows], success)

    def episode_summary(self, team: int) -> dict[str, Any]:
        """A team's episode so far (see :func:`~sb3_formation.env.episodes.episode_summary`)."""
        return episode_summary(
            int(self.episode_lengths[team]),
            float(self.episode_returns[team]),
            self.episode_errors[team].tolist(),
            self.episode_collisions[team].tolist(),
            self.episode_terms[team].tolist(),
            bool(self.success[team]),
            int(self.stages[team]),
        )


def agent_infos(values: np.ndarray, contacts: np.ndarray, success: np.ndarray) -> list[dict[str, Any]]:
    """Agents' info dicts, keys in the order of :data:`INFO_KEYS` (one team's, or many teams' stacked).

    :param values: ``(agents, INFO_VALUES)`` floats: the five errors and distances of :data:`INFO_KEYS`, then the
        reward terms
    :param contacts: ``(agents, 2)`` ints: other agents, then obstacles or walls, touched in the step
    :param success: ``(agents,)`` bools: the agent's team reached the goal
    """
    columns = values.T.tolist()
    touched = contacts.T.tolist()
    columns = [*columns[:5], touched[1], touched[0], success.tolist(), *columns[5:]]
    return [dict(zip(INFO_KEYS, row)) for row in zip(*columns)]


def _row_means(rows: np.ndarray) -> np.ndarray:
    """The mean of each row, as ``rows.mean(axis=1)`` computes it (numpy's sum, then one division) without the
    wrapper's checks, which cost more than the sum for a handful of agents."""
    means: np.ndarray = np.add.reduce(rows, axis=1) / rows.shape[1]
    return means


def _widened(array: np.ndarray, size: int) -> np.ndarray:
    """``array``, or a copy with its second axis grown to ``size`` (the new entries zero)."""
    if array.shape[1] >= size:
        return array
    grown = np.zeros((array.shape[0], size, *array.shape[2:]), dtype=array.dtype)
    grown[:, : array.shape[1]] = array
    return grown


# Compiled kernels: each loops over the given teams and calls, for each, the single-team kernels ------------------------


@numba.njit(cache=True)
def _measure_teams(
    active: np.ndarray,
    positions: np.ndarray,
    starts: np.ndarray,
    neighbours: np.ndarray,
    reference: np.ndarray,
    beta_ref: np.ndarray,
    d_ref: float,
    agent_radius: float,
    circles: np.ndarray,
    circle_counts: np.ndarray,
    walls: np.ndarray,
    wall_counts: np.ndarray,
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
    """The formation (``_measure``, flags) and nearest gaps of the ``active`` teams, into the given arrays; returns the
    nearest gaps (rows of other teams: undefined)."""
    n_slots = positions.shape[0]
    nearest_agent, nearest_obstacle = np.empty(n_slots), np.empty(n_slots)
    for team in active:
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
        team_walls = walls[team, : wall_counts[team]]
        agent_gap, obstacle_gap = nearest_gaps(team_positions, agent_radius, obstacles, team_walls, width, height)
        nearest_agent[start:end] = agent_gap
        nearest_obstacle[start:end] = obstacle_gap
    return nearest_agent, nearest_obstacle


@numba.njit(cache=True)
def _team_terms(
    terms: np.ndarray,
    active: np.ndarray,
    starts: np.ndarray,
    step_counts: np.ndarray,
    angle_errors: np.ndarray,
    bearing_errors: np.ndarray,
    neighbour_distances: np.ndarray,
    centroid_distances: np.ndarray,
    previous_ways: np.ndarray,
    ways: np.ndarray,
    goal_distances: np.ndarray,
    previous_velocities: np.ndarray,
    velocities: np.ndarray,
    neighbours: np.ndarray,
    nearest_agent: np.ndarray,
    nearest_obstacle: np.ndarray,
    constants: np.ndarray,
    max_steps: int,
    team_reward: bool,
) -> None:  # pragma: no cover - compiled
    """The reward terms of the ``active`` teams into ``terms``: each team's ``(terms, n)`` block of ``_reward_terms``,
    the blocks one after the other, flat (other teams' blocks are left as they are)."""
    n_terms = _N_TERMS
    for team in active:
        start, end = starts[team], starts[team + 1]
        block = _reward_terms(
            step_counts[team],
            angle_errors[start:end],
            bearing_errors[start:end],
            neighbour_distances[start:end],
            centroid_distances[start:end],
            previous_ways[team],
            ways[team],
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


@numba.njit(cache=True)
def _observe_teams(
    active: np.ndarray,
    out: np.ndarray,
    values: np.ndarray,
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
    walls: np.ndarray,
    wall_counts: np.ndarray,
    agent_radius: float,
    width: float,
    height: float,
    lidar_range: float,
    d_ref: float,
    d_comm: float,
    eta_c: float,
    step_counts: np.ndarray,
    actions: np.ndarray,
    rewards: np.ndarray,
    goal_distances: np.ndarray,
    terms: np.ndarray,
    contacts: np.ndarray,
    team_means: np.ndarray,
    accumulate: bool,
    episode_lengths: np.ndarray,
    episode_returns: np.ndarray,
    episode_errors: np.ndarray,
    episode_collisions: np.ndarray,
    episode_terms: np.ndarray,
    episode_comm_exceeded: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The ``active`` teams' lidar scans and observations (into ``lidar`` and ``out``), their agents' info values
    (into ``values``: the five errors and distances of ``INFO_KEYS``, then the reward terms) and, with
    ``accumulate``, their episodes' running sums."""
    n_terms = _N_TERMS
    dim = out.shape[1]
    for team in active:
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
            walls[team, : wall_counts[team]],
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
            for term in range(n_terms):
                values[row, 5 + term] = terms[n_terms * start + term * n_agents + agent]
        if not accumulate:
            continue
        # the episode's running sums: agent by agent, each over n (as a team's infos would be summed)
        episode_lengths[team] += 1
        episode_returns[team] += team_means[team]
        comm_exceeded = False
        for agent in range(n_agents):
            row = start + agent
            episode_errors[team, 0] += angle[agent] / n_agents
            episode_errors[team, 1] += bearing[agent] / n_agents
            episode_errors[team, 2] += distance[agent] / n_agents
            episode_collisions[team, 0] += contacts[row, 1]
            episode_collisions[team, 1] += contacts[row, 0]
            for term in range(n_terms):
                episode_terms[team, term] += values[row, 5 + term] / n_agents
            for slot in range(neighbour_distances.shape[1]):
                comm_exceeded = comm_exceeded or neighbour_distances[row, slot] > d_comm
        episode_comm_exceeded[team] += comm_exceeded
