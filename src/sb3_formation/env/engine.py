"""``FormationEngine``: the one implementation of a reset, a step and a team's episode state, for any number of teams.

Every view of the task steps through it: :class:`~sb3_formation.env.formation_env.FormationEnv` is the PettingZoo
view of an engine of one team, :class:`~sb3_formation.env.auto_reset.EngineBlock` adds automatic resets and episode
records for the SB3 ``VecEnv`` and for evaluation. The engine never resets a team by itself: a team whose episode
ended is left as it ended (its last observation is the terminal one) and is not stepped until it is reset.

A step of the live teams is: the engine's :class:`~sb3_formation.env.dynamics.Dynamics` turns the actions into what
each team's Pymunk world is told and reads the world back (each team has its own space, so that a team's numbers never
depend on the others; the formations of a crossing, a *unit* of consecutive teams, share one and see each other's
agents on their lidars' agent channel), then three compiled calls over the stacked arrays of every agent (formation
geometry and nearest gaps; the step's count, reward terms and episode ends; lidar, observations, info values and the episode's
running sums), with numpy between them for the weighted sum of the reward terms and the team means, Python's
``math.hypot`` for the goal distance, and the engine's :class:`~sb3_formation.env.progress.GoalProgress` for the way
to the goal that the goal term rewards. A reset measures the new team with the same kernels. ``docs/design.md``
follows one step through. Under the task's disturbances (``FormationConfig.disturbances``) the engine's
:class:`~sb3_formation.env.disturbed.Disturber` turns the actions sent into what the motors apply, and what the world
is into what the agents sense and, late, observe; rewards, infos and contacts stay the true world's. In the ideal
world there is no disturber and the step is as described. Under the task's failures an agent's motors may stop at the
end of a step (:meth:`FormationEngine.fail`): from the measure of that step on, its team is the ring of its flying
agents.

The engine keeps its numbers in the few structures of :mod:`~sb3_formation.env.stacked`; a kernel takes each as the
plain tuple of its fields. Arrays that the engine returns are never written again: the next step makes new ones, and a
reset copies an array before it writes the reset team's rows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import IntEnum
from typing import Any, NamedTuple, cast

import numba
import numpy as np
from gymnasium.utils import seeding

from sb3_formation.env.config import INFO_KEYS, REWARD_TERMS, FormationConfig
from sb3_formation.env.disturbed import Disturber, FailureSchedule, SensedTeams
from sb3_formation.env.dynamics import Dynamics, DynamicsModel, LateActions, dynamics_model
from sb3_formation.env.episodes import episode_summary
from sb3_formation.env.geometry import (
    FormationState,
    _measure_into,
    agent_errors,
    flying_ring,
    interior_angle_deg,
    reference_bearings,
    ring_neighbours,
)
from sb3_formation.env.observations import _fill_observations, observation_fields
from sb3_formation.env.progress import GOAL_PROGRESS_CLASSES, GoalProgress
from sb3_formation.env.rewards import RewardConstants, _reward_terms, combine_rewards, nearest_gaps, reward_constants
from sb3_formation.env.scenarios import Scenario, crossing_scenario
from sb3_formation.env.scenes import check_scenes_fit, scenes_named
from sb3_formation.env.sensors import AGENT_CHANNEL, OBSTACLE_CHANNEL, Lidar, LidarLayout, lidar_ranges, ray_directions
from sb3_formation.env.stacked import (
    Constants,
    Episodes,
    Fields,
    Formations,
    Shapes,
    StepArrays,
    StepTeams,
    team_formation,
    widened,
)
from sb3_formation.env.state import TeamState
from sb3_formation.env.world import World

_N_TERMS = len(REWARD_TERMS)
#: the arrays of :class:`~sb3_formation.env.stacked.StepArrays` that the engine returns (never written again)
_RETURNED = ("positions", "velocities", "contacts", "observations", "info_values")


class InfoColumn(IntEnum):
    """The columns of a step's info values ``(agents, INFO_VALUES)``: the keys of :data:`INFO_KEYS` that the step
    measures (each named as its key, in upper case), then from :attr:`FIRST_TERM` on the reward terms in the order of
    ``REWARD_TERMS`` (:func:`agent_infos` adds the contacts and success)."""

    ANGLE_ERROR_DEG = 0  #: |beta^ref - beta^i| (deg)
    BEARING_ERROR = 1  #: mean over the two neighbours of |g_j^{i,ref} - g_j^i|
    NEIGHBOUR_DISTANCE_ERROR = 2  #: mean over the two neighbours of max(d_j^i - d^ref, 0) (m)
    CENTROID_DISTANCE = 3  #: |p^i - p^c| (m)
    GOAL_DISTANCE = 4  #: the team's centroid-goal distance (m)
    FIRST_TERM = 5  #: reward term k (before its coefficient) is column ``FIRST_TERM + k``


#: the number of columns of a step's info values (:class:`InfoColumn`)
INFO_VALUES = InfoColumn.FIRST_TERM + _N_TERMS


class ContactColumn(IntEnum):
    """The columns of a step's contacts ``(agents, 2)``: what each agent touched in the step."""

    AGENTS = 0  #: other agents
    OBSTACLES = 1  #: obstacles or walls
    #: of those, moving obstacles that ran into the agent: it commanded no velocity towards them in the step (it was
    #: braking, standing or moving away); every other contact is one the agent drove into
    RAMMED = 2


class EngineStep(NamedTuple):
    """What a step of a :class:`FormationEngine` gives, for every agent (rows) or team; rows of teams that were not
    stepped hold what they held before the step (rewards: 0)."""

    observations: np.ndarray  #: ``(agents, dim)`` float32
    rewards: np.ndarray  #: ``(agents,)``
    terminated: np.ndarray  #: ``(teams,)``: the centroid reached the goal in this step
    truncated: np.ndarray  #: ``(teams,)``: the step limit T_s ended the episode
    info_values: np.ndarray  #: ``(agents, INFO_VALUES)`` (:class:`InfoColumn`)
    contacts: np.ndarray  #: ``(agents, 3)`` (:class:`ContactColumn`) touched in the step
    positions: np.ndarray  #: ``(agents, 2)`` (m)
    velocities: np.ndarray  #: ``(agents, 2)`` (m/s)


class FormationEngine:
    """Teams of one task (they may differ in ``n_agents`` only), reset one by one and stepped together.

    Agents are stacked one team after the other (team t holds rows ``starts[t]:starts[t + 1]``, agent 0 first). Each
    team has its own scenario generator, curriculum stage, Pymunk world and lidar. The numbers of every team are in
    :attr:`constants`, :attr:`shapes`, :attr:`formations`, :attr:`latest` and :attr:`episodes`
    (:mod:`~sb3_formation.env.stacked`).

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
        self.starts = starts = np.concatenate([[0], np.cumsum(sizes)])
        n_teams = len(sizes)
        #: how many consecutive teams fly one scene together in one world, a unit (a crossing's formations; 1: every
        #: team alone)
        self.unit_size = unit_size = scenes_named(config.scenes).formations
        if unit_size > 1 and (n_teams % unit_size or len(set(sizes.tolist())) > 1):
            raise ValueError(
                f"the {config.scenes!r} scenes fly {unit_size} formations together: give a multiple of {unit_size} "
                f"teams of one size, got teams of {sizes.tolist()}"
            )
        #: the first row of each unit (``unit_size`` consecutive teams sharing a world), and the number of rows, last
        self.unit_starts = starts[::unit_size]
        #: the fields of an agent's observation (Table 3.1), in order
        self.observation_fields = observation_fields(config)
        self.observation_dim = sum(field.size for field in self.observation_fields)
        #: team size -> (teams of that size, their agents' rows in team order): the groups of the stacked numpy work
        self._groups = {
            int(size): (teams, np.concatenate([np.arange(starts[t], starts[t + 1]) for t in teams]))
            for size in np.unique(sizes)
            for teams in [np.flatnonzero(sizes == size)]
        }
        self._single_size = len(self._groups) == 1
        # per-team objects
        self.lidars = [
            Lidar(c.lidar_rays, c.lidar_range, c.agent_radius, c.world_width, c.world_height, ring_neighbours(c.n_agents))
            for c in self.configs
        ]
        self.worlds: list[World | None] = [None] * n_teams
        self._moving = np.zeros(n_teams, dtype=bool)  # teams whose scenario has moving obstacles
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
        #: what the task's dynamics mean, how actions move the agents, and what the goal term rewards progress along
        self.model: DynamicsModel = dynamics_model(config)
        self.dynamics: Dynamics = self.model.engine_dynamics(self.unit_starts)  # it moves worlds: units
        self.progress: GoalProgress = GOAL_PROGRESS_CLASSES[config.goal_progress](self.configs, starts)
        #: teams in an episode (reset and not ended since)
        self.live = np.zeros(n_teams, dtype=bool)
        #: teams whose centroid reached the goal in their last step
        self.success = np.zeros(n_teams, dtype=bool)
        self._every_team = StepTeams(np.arange(n_teams), list(range(n_teams)), slice(None), None, everyone=True)
        self.constants = _constants(self.configs, starts)
        n_slots = int(starts[-1])
        self.shapes = Shapes.empty(n_teams, n_slots)
        self.formations = Formations.zeros(n_teams, n_slots)
        self.latest = StepArrays.zeros(n_teams, n_slots, self.observation_dim, INFO_VALUES, _N_TERMS)
        self.episodes = Episodes.zeros(n_teams, n_slots, config.lidar_rays, _N_TERMS)
        # the fields of the structures that are never replaced, and of the reward constants, as the kernels take them
        self._fixed_fields = tuple(self.constants), tuple(self.formations), tuple(self.episodes)
        self._reward_fields = tuple(reward_constants(config))
        self._shape_fields = tuple(self.shapes)  # again at each reset (_load_shapes)
        #: the task's disturbances of the signals, drawn and applied (``None`` in the ideal world, which then runs as it
        #: always did), and its agents' failures (``None``: no agent fails)
        signals = config.disturbances.signals
        self.disturber = None if signals.is_ideal else Disturber(config, starts, self.observation_dim)
        failures = config.disturbances.failures
        self.failures = None if failures.is_ideal else FailureSchedule(failures, sizes)
        self._failed_teams: set[int] = set()  # teams with an agent that failed in this episode
        #: the formations the agents measure from their position estimates (the true ones without localisation errors)
        self._sensed_fields = self._fixed_fields[1]
        for team, seed in enumerate(self.generator_seeds):
            self._seed_draws(team, seed)
        if self.disturber is not None:
            if self.disturber.localises:
                self._sensed_fields = tuple(Formations.zeros(n_teams, n_slots))
        self._no_errors = (np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0), dtype=bool))
        #: what the agents sensed at the last reset or step (``None`` in the ideal world): what a simulator publishes
        self.sensed: SensedTeams | None = None

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
        self._seed_draws(team, self.generator_seeds[team])

    def _seed_draws(self, team: int, seed: int) -> None:
        """Seed the disturbances' and the failures' streams of a team from its scenario seed."""
        if self.disturber is not None:
            self.disturber.seed(team, seed)
        if self.failures is not None:
            self.failures.seed(team, seed)

    # Reset --------------------------------------------------------------------------------------------------------

    def reset(self, team: int, seed: int | None = None, scenario: Scenario | Sequence[Scenario] | None = None) -> np.ndarray:
        """Start a team's next episode: draw its scenario of the team's stage (or place ``scenario``) and measure it.
        In a crossing (:attr:`unit_size` > 1) the first team of a unit starts every formation of it, from one draw of
        its own generator (``scenario``: the formations' placements, one per team).

        :param team: the team (in a crossing, the first of its unit)
        :param seed: re-seed the team's generator first (see :meth:`seed`)
        :param scenario: place this instead of drawing one (validated against the team's task)
        :return: the team's ``(n, dim)`` observations (a copy)
        :raises ValueError: a team of a crossing that is not the first of its unit, or a placement that does not fit
        """
        config, unit_size = self.configs[team], self.unit_size
        if team % unit_size:
            raise ValueError(f"team {team} flies in the crossing of team {team - team % unit_size}: reset that team")
        if seed is not None:
            self.seed(team, seed)
        if scenario is None:
            parts = scenes_named(config.scenes).draw_formations(config, int(self.stages[team]), self.generators[team])
        else:
            given = [scenario] if unit_size == 1 else list(cast("Sequence[Scenario]", scenario))
            if len(given) != unit_size or not all(isinstance(part, Scenario) for part in given):
                kinds = type(scenario).__name__
                wanted = "a Scenario" if unit_size == 1 else f"{unit_size} Scenarios, one per formation"
                raise TypeError(f"the scenario must be {wanted}, got {kinds}")
            parts = tuple(cast("list[Scenario]", given))
            for part in parts:
                part.validate(config)
        world = self._place(team, parts)
        episodes = self.episodes
        # arrays that were returned are copied before their rows change (see the module docstring)
        latest = self.latest = self.latest._replace(**{name: getattr(self.latest, name).copy() for name in _RETURNED})
        self.dynamics.reset(slice(int(self.starts[team]), int(self.starts[team + unit_size])), world)
        for member, part in enumerate(parts, start=team):
            rows, places = self.team_rows(member), self._world_rows(member)
            latest.positions[rows] = world.positions[places]
            latest.velocities[rows] = world.velocities[places]
            latest.contacts[rows] = 0
            latest.terms[_N_TERMS * rows.start : _N_TERMS * rows.stop] = 0.0  # a reset's infos hold no reward terms
            if self.disturber is not None:
                self.disturber.reset(member, rows)
            self._clear_episode(member, part.goal)
            if self.failures is not None:
                self.failures.reset(member)
                for failing, agent in self.failures.due([member], episodes.step_counts):  # at step 0: failed from the start
                    self.fail(failing, agent)
            active = np.array([member])
            self._measure(active, latest.positions)
            centroid = self.formations.centroids[member]
            latest.goal_distances[member] = math.hypot(*(episodes.goals[member] - centroid).tolist())
            latest.ways[member] = self.progress.reset(member, part, centroid, float(latest.goal_distances[member]))
            episodes.previous_offsets[member] = episodes.goals[member] - centroid  # no step before: the offset now
            self._observe(active, rows, np.zeros(self.n_teams), accumulate=False)
        observations: np.ndarray = latest.observations[self.team_rows(team)].copy()
        return observations

    def _world_rows(self, team: int) -> slice:
        """A team's agents' rows in its world (its formation's place in its unit's)."""
        first = int(self.starts[team] - self.unit_starts[team // self.unit_size])
        return slice(first, first + int(self.sizes[team]))

    def _place(self, team: int, parts: Sequence[Scenario]) -> World:
        """Place a unit's formations ``parts`` (its first ``team``'s first) in its world, made at its first reset, and
        give each team's lidar its shapes: the obstacles, the movers, and the other formations' agents."""
        world = self.worlds[team]
        placed = parts[0] if len(parts) == 1 else crossing_scenario(parts)
        if world is None:
            world = World(self.configs[team], placed)
        else:
            world.place(placed)
        others = np.zeros((world.n_agents - int(self.sizes[team]), 3))  # the other formations' agents (_see_others)
        others[:, 2] = self.config.agent_radius
        for member, part in enumerate(parts, start=team):
            self.worlds[member], self.scenarios[member] = world, part
            self._moving[member] = bool(part.movers)
            lidar = self.lidars[member]
            lidar.set_obstacles(np.vstack([part.obstacles, world.movers.circles, others]), part.walls, agents=len(others))
            self._load_shapes(member, lidar.layout)
        if len(parts) > 1:
            self._see_others(team // self.unit_size)
        return world

    def _clear_episode(self, team: int, goal: np.ndarray) -> None:
        """Start a team's episode towards ``goal``: no step, no memory of one, no sums; live, no success."""
        rows, episodes = self.team_rows(team), self.episodes
        episodes.previous_actions[rows] = 0.0
        episodes.previous_rewards[rows] = 0.0
        episodes.goals[team] = goal
        episodes.step_counts[team] = 0
        episodes.returns[team] = episodes.comm_exceeded[team] = 0
        episodes.errors[team] = episodes.term_sums[team] = episodes.collisions[team] = 0
        self.live[team], self.success[team] = True, False
        if team in self._failed_teams:  # every agent flies again, on the ring of n
            self._failed_teams.discard(team)
            n_agents = rows.stop - rows.start
            self._set_ring(team, np.ones(n_agents, dtype=bool), ring_neighbours(n_agents), reference_bearings(n_agents))

    # Failures -----------------------------------------------------------------------------------------------------

    def fail(self, team: int, agent: int) -> None:
        """Stop an agent's motors for the rest of its team's episode (``docs/disturbances.md``, "Agents that fail"):
        its world halts it, the others' lidars see it as an obstacle, and the flying agents close their ring without
        it (:func:`~sb3_formation.env.geometry.flying_ring`: neighbours, the reference bearings and beta^ref of the
        ring's size), from the measure that follows on. Its team's centroid, range flag, collision term, team averages
        and episode sums are the flying agents'.

        :param team: the team
        :param agent: the agent's index in its team
        :raises ValueError: the agent does not fly, or fewer than 3 agents would
        """
        rows = self.team_rows(team)
        flying = self.constants.flying[rows].copy()
        if not 0 <= agent < len(flying) or not flying[agent]:
            raise ValueError(f"agent {agent} of team {team} does not fly (flying: {np.flatnonzero(flying).tolist()})")
        flying[agent] = False
        ring = flying_ring(flying)
        references = self.constants.reference_bearings[rows].copy()
        references[flying] = reference_bearings(ring.size)[ring.places[flying]]
        self._set_ring(team, flying, ring.neighbours, references)
        cast(World, self.worlds[team]).halt(self._world_rows(team).start + agent)
        self._failed_teams.add(team)
        if self.unit_size > 1:
            self._see_others(team // self.unit_size)

    def _set_ring(self, team: int, flying: np.ndarray, neighbours: np.ndarray, references: np.ndarray) -> None:
        """A team's flying agents, their ring neighbours and reference bearings (into :attr:`constants`), beta^ref of
        the ring's size, and its lidar's view of them."""
        rows, constants = self.team_rows(team), self.constants
        constants.flying[rows], constants.neighbours[rows], constants.reference_bearings[rows] = flying, neighbours, references
        constants.beta_ref[team] = interior_angle_deg(int(flying.sum()))
        lidar = self.lidars[team]
        lidar.set_flying(flying, neighbours)
        self._load_shapes(team, lidar.layout)

    def _load_shapes(self, team: int, layout: LidarLayout) -> None:
        """Put a team's lidar layout (its obstacles and agents as circles, who sees which, their channels, its walls)
        into :attr:`shapes`, widened when the team has more circles or walls than any team had."""
        count, wall_count, rows = len(layout.channels), len(layout.walls), self.team_rows(team)
        old = self.shapes
        shapes = self.shapes = Shapes(
            widened(old.circles, count),
            widened(old.visible, count),
            widened(old.channels, count),
            old.circle_counts,
            widened(old.walls, wall_count),
            old.wall_counts,
        )
        shapes.circles[team, :count] = layout.circles
        shapes.visible[rows, :count] = layout.visible
        shapes.channels[team, :count] = layout.channels
        shapes.circle_counts[team] = count
        shapes.walls[team, :wall_count] = layout.walls
        shapes.wall_counts[team] = wall_count
        self._shape_fields = tuple(shapes)

    # Step ---------------------------------------------------------------------------------------------------------

    def step(self, actions: np.ndarray) -> EngineStep:
        """Step every live team under its agents' rows of ``actions``; teams that end stay ended until reset.

        :param actions: ``(agents, 2)`` finite actions within [-1, 1] (the views check and clip them), every team's
            agents one after the other; the rows of teams that are not live are ignored
        """
        stepped = self._every_team if self.live.all() else self._live_teams()
        if stepped.active.size == 0:  # nothing to step (a block of an evaluation whose episodes are all played)
            return self._unchanged(len(actions))
        previous, episodes, centroids = self.latest, self.episodes, self.formations.centroids
        positions, velocities, contacts = self._move(actions, stepped)  # forces, physics, state (steps 1-3 of design.md)
        if self.failures is not None:  # motors that stop at the end of this step
            for team, agent in self.failures.due(stepped.teams, self.episodes.step_counts + 1):
                self.fail(team, agent)
        self._measure(stepped.active, positions)  # formation (4)
        goal_distances = self._goal_distances(stepped, previous.goal_distances)  # goal distance (5)
        ways = self.progress.ways(previous.ways, goal_distances, centroids, stepped)  # and the way the goal term rewards
        self.latest = latest = self._next_arrays(stepped, positions, velocities, contacts, goal_distances, ways)
        ends = self._count_and_reward(stepped.active)  # reward terms (6), and which teams end (7)
        rewards, team_means = self._combine(latest.terms)
        terminated, truncated = self._end_episodes(stepped, *ends)
        # what the agents observe of this step at the next: their actions, and rewards with the thesis's goal term
        stepped.write(episodes.previous_actions, actions)
        before_and_after = (previous.goal_distances, goal_distances)
        observed = self.progress.observed_rewards(rewards, latest.terms, before_and_after, stepped, self._combine)
        stepped.write(episodes.previous_rewards, observed)
        self._observe(stepped.active, stepped.rows, team_means, accumulate=True)  # lidar, observations, infos, sums (8)
        return EngineStep(
            latest.observations, rewards, terminated, truncated, latest.info_values, contacts, positions, velocities
        )

    def _move(self, actions: np.ndarray, stepped: StepTeams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The :attr:`dynamics` moves the worlds of the stepped teams under the actions their motors apply (those sent,
        or what the :attr:`disturber` makes of them): every agent's positions, velocities and contacts after the step
        (new arrays; the other teams' rows as they were; in a crossing, a unit's teams whose episodes ended stand in
        its world, halted, and their rows follow them)."""
        previous, late = self.latest, cast("LateActions | None", None)
        units = stepped if self.unit_size == 1 else self._live_units()
        if self.disturber is not None and self.disturber.acts:
            moving_teams = units.teams if self.unit_size == 1 else [t for u in units.teams for t in self._unit_teams(u)]
            actions, late = self.disturber.act(actions, moving_teams, self.episodes.step_counts)
        worlds = cast("list[World]", self.worlds[:: self.unit_size])
        moving = [unit for unit in units.teams if self._moving[unit * self.unit_size]] if self._moving.any() else []
        for unit in moving:
            worlds[unit].move_obstacles()
        moved = self.dynamics.move(actions, previous.velocities, worlds, units, late)
        for unit in moving:  # the lidar's and the nearest gaps' circles: the static obstacles, the movers, the agents
            movers = worlds[unit].movers
            for team in self._unit_teams(unit):
                first = len(cast(Scenario, self.scenarios[team]).obstacles)
                self.shapes.circles[team, first : first + len(movers.positions), :2] = movers.positions
                self.lidars[team].layout.circles[first : first + len(movers.positions), :2] = movers.positions  # ROS
        if self.unit_size > 1:
            for unit in units.teams:
                self._see_others(unit)
        contacts = np.zeros(previous.contacts.shape, dtype=np.int64) if units.everyone else previous.contacts.copy()
        if units.rows is not None:
            contacts[units.rows] = 0
        for unit, counts in zip(units.teams, moved.touched):
            if counts is not None:
                contacts[self.unit_starts[unit] : self.unit_starts[unit + 1]] = np.transpose(counts)
        positions = units.merged(previous.positions, moved.positions)
        return positions, units.merged(previous.velocities, moved.velocities), contacts

    def _unit_teams(self, unit: int) -> range:
        """The teams of a unit (formations flying one scene together in one world)."""
        return range(unit * self.unit_size, (unit + 1) * self.unit_size)

    def _live_units(self) -> StepTeams:
        """The units with a team in an episode: every agent of theirs moves (a team that ended, halted)."""
        live = self.live.reshape(-1, self.unit_size).any(axis=1)
        active = np.flatnonzero(live)
        rows = None if live.all() else np.repeat(live, np.diff(self.unit_starts))
        return StepTeams(active, active.tolist(), slice(None) if rows is None else active, rows, everyone=rows is None)

    def _see_others(self, unit: int) -> None:
        """Show each formation of a crossing's unit the others' agents where its world has them: circles of the agent
        channel while they fly, of the obstacle channel once halted (failed, or their formation's episode ended)."""
        world = cast(World, self.worlds[unit * self.unit_size])
        states, halted = world.agent_states[:, :2], world.halted
        for team in self._unit_teams(unit):
            own = self._world_rows(team)
            others, channels = (
                np.delete(states, own, axis=0),
                np.where(np.delete(halted, own), OBSTACLE_CHANNEL, AGENT_CHANNEL),
            )
            last = int(self.shapes.circle_counts[team]) - int(self.sizes[team])
            first = last - len(others)
            layout = self.lidars[team].layout
            self.shapes.circles[team, first:last, :2] = layout.circles[first:last, :2] = others
            self.shapes.channels[team, first:last] = layout.channels[first:last] = channels

    def _next_arrays(
        self,
        stepped: StepTeams,
        positions: np.ndarray,
        velocities: np.ndarray,
        contacts: np.ndarray,
        goal_distances: np.ndarray,
        ways: np.ndarray,
    ) -> StepArrays:
        """The arrays of a step: the values it measured, new arrays for its observations, info values and reward
        terms (copies of the last step's when some teams do not step), and the values it compares with."""
        previous, everyone, n_terms = self.latest, stepped.everyone, _N_TERMS * len(positions)
        return StepArrays(
            positions,
            velocities,
            previous.velocities,
            contacts,
            np.empty_like(previous.observations) if everyone else previous.observations.copy(),
            np.empty_like(previous.info_values) if everyone else previous.info_values.copy(),
            np.empty(n_terms) if everyone else np.zeros(n_terms),
            goal_distances,
            ways,
            previous.ways,
        )

    def _live_teams(self) -> StepTeams:
        """The teams in an episode, when some are not."""
        active = np.flatnonzero(self.live)
        return StepTeams(active, active.tolist(), active, np.repeat(self.live, self.sizes), everyone=False)

    def _unchanged(self, n_slots: int) -> EngineStep:
        """A step of no team: every array as it was, no reward, no end."""
        latest, ended = self.latest, np.zeros(self.n_teams, dtype=bool)
        unchanged = (latest.info_values, latest.contacts, latest.positions, latest.velocities)
        return EngineStep(latest.observations, np.zeros(n_slots), ended, ended.copy(), *unchanged)

    def _goal_distances(self, stepped: StepTeams, previous: np.ndarray) -> np.ndarray:
        """Every team's centroid-goal distance (m) after a step (a new array; teams not stepped: as they were)."""
        distances: np.ndarray = previous.copy()
        offsets = self.episodes.goals[stepped.pick] - self.formations.centroids[stepped.pick]
        for team, (x, y) in zip(stepped.teams, offsets.tolist()):
            distances[team] = math.hypot(x, y)  # Python's hypot: numba's and numpy's round otherwise
        return distances

    def _end_episodes(
        self, stepped: StepTeams, terminated: np.ndarray, truncated: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The stepped teams that reached the goal (``terminated``) or T_s without it (``truncated``) leave :attr:`live`;
        the first succeed."""
        self.success[stepped.pick] = terminated[stepped.pick]
        self.live = self.live & ~(terminated | truncated)
        if self.unit_size > 1:  # a crossing's formation that ended stands where it is until its unit's next reset
            for team in np.flatnonzero(terminated | truncated).tolist():
                places = self._world_rows(team)
                for place in range(places.start, places.stop):
                    cast(World, self.worlds[team]).halt(place)
                self._see_others(team // self.unit_size)
        return terminated, truncated

    def _measure(self, active: np.ndarray, positions: np.ndarray) -> None:
        """Remember the goal offsets of the ``active`` teams and measure their formation and nearest gaps at
        ``positions`` (into :attr:`episodes` and :attr:`formations`)."""
        constants, formations, _ = self._fixed_fields
        offsets = (self.episodes.goals, self.episodes.previous_offsets)
        _measure_teams(active, constants, self._shape_fields, positions, formations, offsets)

    def _count_and_reward(self, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Count the step of the ``active`` teams, put their reward terms into :attr:`latest`, and return which of them
        terminated and which were truncated."""
        constants, formations, _ = self._fixed_fields
        latest, step_counts = tuple(self.latest), self.episodes.step_counts
        ends: tuple[np.ndarray, np.ndarray] = _terms_and_ends(
            active, constants, formations, latest, step_counts, self._reward_fields
        )
        return ends

    def _observe(self, active: np.ndarray, rows: slice | np.ndarray | None, team_means: np.ndarray, accumulate: bool) -> None:
        """Scan, observe and fill the info values of the ``active`` teams (their agents' ``rows``, ``None``: every
        agent's); with ``accumulate``, add the step to their episodes' running sums. With disturbances the agents
        observe what they sense (:meth:`~sb3_formation.env.disturbed.Disturber.sense`), late
        (:meth:`~sb3_formation.env.disturbed.Disturber.delay_observations`)."""
        constants, formations, episodes = self._fixed_fields
        picked = slice(None) if rows is None else rows
        observed = self.dynamics.observe(picked)
        latest = self.latest
        sensing = (latest.positions, latest.velocities, formations, *self._no_errors)
        disturber = self.disturber
        if disturber is not None:
            sensed = self.sensed = disturber.sense(latest.positions, latest.velocities, active.tolist(), drift=accumulate)
            observed = self._sensed_extras(observed, picked, sensed)
            if disturber.localises:  # the formation the agents measure, and the centroid offset they compare with
                goals, offsets, centroids = self.episodes.goals, self.episodes.previous_offsets, self._sensed_fields[0]
                if accumulate:
                    offsets[active] = goals[active] - centroids[active]
                _store_formations(active, constants, sensed.positions, self._sensed_fields)
                if not accumulate:
                    offsets[active] = goals[active] - centroids[active]
            errors = (sensed.heading_errors, sensed.beam_noise, sensed.dropped)
            sensing = (sensed.positions, sensed.velocities, self._sensed_fields, *errors)
        shapes = self._shape_fields
        _observe_teams(
            active, constants, shapes, formations, tuple(latest), episodes, observed, team_means, accumulate, sensing
        )
        if disturber is not None:
            disturber.delay_observations(latest.observations, active.tolist(), self.episodes.step_counts)

    def _sensed_extras(self, observed: np.ndarray, rows: slice | np.ndarray, sensed: SensedTeams) -> np.ndarray:
        """What the dynamics add to the observation (:meth:`Dynamics.observe`), read at the agents' heading estimates."""
        headings = self.dynamics.headings_of(slice(None))
        if not self.disturber or not self.disturber.localises or headings is None or observed.shape[1] == 0:
            return observed
        extras: np.ndarray = observed.copy()
        extras[rows] = self.model.observed_values((headings + sensed.heading_errors)[rows])
        return extras

    def _combine(self, terms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every agent's reward (:func:`~sb3_formation.env.rewards.combine_rewards`, the teams of one size at once)
        and every team's mean reward.

        :param terms: every team's ``(terms, n)`` block, one after the other, flat
        :return: rewards ``(agents,)`` and team means ``(teams,)`` (over the flying agents)
        """
        clip = self.config.reward_clip
        if self._single_size:  # one reshape: each team's block is its (terms, n) matrix
            grouped = combine_rewards(terms.reshape(self.n_teams, _N_TERMS, -1), self._coefficients, clip)
            rewards, team_means = grouped.reshape(-1), _row_means(grouped)
        else:
            rewards, team_means = np.empty(int(self.starts[-1])), np.empty(self.n_teams)
            for n_agents, (teams, rows) in self._groups.items():
                blocks = np.stack([terms[_N_TERMS * self.starts[t] : _N_TERMS * self.starts[t + 1]] for t in teams])
                group = combine_rewards(blocks.reshape(len(teams), _N_TERMS, n_agents), self._coefficients[teams], clip)
                rewards[rows], team_means[teams] = group.reshape(-1), _row_means(group)
        for team in self._failed_teams:
            team_rows = self.team_rows(team)
            flown = rewards[team_rows][self.constants.flying[team_rows]]
            team_means[team] = np.add.reduce(flown) / len(flown)
        return rewards, team_means

    # Reading a team ------------------------------------------------------------------------------------------------

    def formation(self, team: int) -> FormationState:
        """A team's formation now (copies)."""
        view = team_formation(team, self.starts, self.formations)
        return FormationState._make(np.copy(value) if isinstance(value, np.ndarray) else value for value in view)

    def team_state(self, team: int) -> TeamState:
        """A frozen snapshot of a team now (after its last reset or step)."""
        if self.worlds[team] is None:
            raise RuntimeError(f"team {team} has not been reset")
        rows, latest, episodes = self.team_rows(team), self.latest, self.episodes
        values = latest.info_values[rows]
        scenario = cast(Scenario, self.scenarios[team])  # placed with the team's world
        world = cast(World, self.worlds[team])
        movers, still = world.movers, np.zeros((len(scenario.obstacles), 2))
        others = np.delete(world.agent_states[:, :2], self._world_rows(team), axis=0) if self.unit_size > 1 else None
        return TeamState(
            step=int(episodes.step_counts[team]),
            positions=latest.positions[rows],
            velocities=latest.velocities[rows],
            goal=episodes.goals[team],
            obstacles=np.vstack([scenario.obstacles, movers.circles]),
            obstacle_velocities=np.vstack([still, movers.velocities]) if scenario.movers else None,
            moving=len(scenario.movers),
            walls=cast(np.ndarray, scenario.walls),
            neighbours=self.constants.neighbours[rows],
            contacts_agent=latest.contacts[rows, ContactColumn.AGENTS],
            contacts_obstacle=latest.contacts[rows, ContactColumn.OBSTACLES],
            angle_errors_deg=values[:, InfoColumn.ANGLE_ERROR_DEG],
            bearing_errors=values[:, InfoColumn.BEARING_ERROR],
            neighbour_distance_errors=values[:, InfoColumn.NEIGHBOUR_DISTANCE_ERROR],
            centroid=self.formations.centroids[team],
            goal_distance=float(latest.goal_distances[team]),
            lidar_obstacles=episodes.lidar[OBSTACLE_CHANNEL, rows],
            lidar_agents=episodes.lidar[AGENT_CHANNEL, rows],
            headings=self.dynamics.headings_of(rows),
            flying=self.constants.flying[rows] if team in self._failed_teams else None,
            others=others,
        )

    def infos(self, team: int) -> list[dict[str, Any]]:
        """A team's agents' info dicts after its last reset or step (keys: :data:`INFO_KEYS`)."""
        rows = self.team_rows(team)
        success = np.full(rows.stop - rows.start, self.success[team])
        return agent_infos(self.latest.info_values[rows], self.latest.contacts[rows], success)

    def episode_summary(self, team: int) -> dict[str, Any]:
        """A team's episode so far (see :func:`~sb3_formation.env.episodes.episode_summary`)."""
        episodes = self.episodes
        return episode_summary(
            int(episodes.step_counts[team]),
            float(episodes.returns[team]),
            episodes.errors[team].tolist(),
            episodes.collisions[team].tolist(),
            episodes.term_sums[team].tolist(),
            bool(self.success[team]),
            int(self.stages[team]),
            moving=bool(self._moving[team]),
            failed=None if self.failures is None else int((~self.constants.flying[self.team_rows(team)]).sum()),
        )


def agent_infos(values: np.ndarray, contacts: np.ndarray, success: np.ndarray) -> list[dict[str, Any]]:
    """Agents' info dicts, keys in the order of :data:`INFO_KEYS` (one team's, or many teams' stacked).

    :param values: ``(agents, INFO_VALUES)`` floats (:class:`InfoColumn`)
    :param contacts: ``(agents, 3)`` ints (:class:`ContactColumn`)
    :param success: ``(agents,)`` bools: the agent's team reached the goal
    """
    columns = values.T.tolist()
    touched = contacts.T.tolist()
    first_term = InfoColumn.FIRST_TERM
    columns = [
        *columns[:first_term],
        touched[ContactColumn.OBSTACLES],
        touched[ContactColumn.AGENTS],
        touched[ContactColumn.RAMMED],
        success.tolist(),
        *columns[first_term:],
    ]
    return [dict(zip(INFO_KEYS, row)) for row in zip(*columns)]


def _row_means(rows: np.ndarray) -> np.ndarray:
    """The mean of each row, as ``rows.mean(axis=1)`` computes it (numpy's sum, then one division) without the
    wrapper's checks, which cost more than the sum for a handful of agents."""
    means: np.ndarray = np.add.reduce(rows, axis=1) / rows.shape[1]
    return means


def _constants(configs: list[FormationConfig], starts: np.ndarray) -> Constants:
    """An engine's constants: its teams' rows, neighbours and reference bearings, and the task's numbers.

    :param configs: every team's task configuration (they differ in ``n_agents`` only)
    :param starts: the first row of each team, then the number of rows
    """
    config, sizes = configs[0], [team_config.n_agents for team_config in configs]
    return Constants(
        starts=starts,
        neighbours=np.concatenate([ring_neighbours(n) for n in sizes]).astype(np.int64),
        reference_bearings=np.ascontiguousarray(np.concatenate([reference_bearings(n) for n in sizes])),
        beta_ref=np.array([team_config.beta_ref_deg for team_config in configs]),
        flying=np.ones(int(starts[-1]), dtype=bool),
        directions=ray_directions(config.lidar_rays),
        d_ref=float(config.d_ref),
        d_comm=float(config.d_comm),
        eta_c=float(config.eta_c),
        agent_radius=float(config.agent_radius),
        width=float(config.world_width),
        height=float(config.world_height),
        lidar_range=float(config.lidar_range),
        observe_reference=bool(config.observe_reference_bearings),
    )


# Compiled kernels: each loops over the given teams and calls, for each, the single-team kernels. They take each structure
# as the plain tuple of its fields and name the fields again (see sb3_formation.env.stacked) -------------------------------


@numba.njit(cache=True)
def _measure_teams(
    active: np.ndarray,
    constant_fields: Fields,
    shape_fields: Fields,
    positions: np.ndarray,
    formation_fields: Fields,
    offsets: tuple[np.ndarray, np.ndarray],
) -> None:  # pragma: no cover - compiled
    """For each of the ``active`` teams, remember its goal offset c_g^v = p^g - p^c before the step (the observation
    compares with it), then measure its formation and its agents' nearest gaps at ``positions`` into the formations.

    :param offsets: every team's goal (m) and the goal offsets (m) remembered
    """
    constants, shapes, formations = Constants(*constant_fields), Shapes(*shape_fields), Formations(*formation_fields)
    goals, previous_offsets = offsets
    starts, centroids, circles, circle_counts = constants.starts, formations.centroids, shapes.circles, shapes.circle_counts
    walls, wall_counts = shapes.walls, shapes.wall_counts
    for team in active:
        start, end = starts[team], starts[team + 1]
        previous_offsets[team, 0] = goals[team, 0] - centroids[team, 0]
        previous_offsets[team, 1] = goals[team, 1] - centroids[team, 1]
        team_positions = positions[start:end]
        _store_formation(team, constants, team_positions, formations)
        obstacles = circles[team, : circle_counts[team] - (end - start)]  # the lidar's circles: obstacles, then agents
        agent_gap, obstacle_gap = nearest_gaps(
            team_positions,
            constants.agent_radius,
            obstacles,
            walls[team, : wall_counts[team]],
            constants.width,
            constants.height,
            constants.flying[start:end],
        )
        formations.nearest_agent_distances[start:end] = agent_gap
        formations.nearest_obstacle_gaps[start:end] = obstacle_gap


@numba.njit(cache=True)
def _store_formation(
    team: int, constants: Constants, positions: np.ndarray, formations: Formations
) -> None:  # pragma: no cover - compiled
    """A team's formation at its agents' ``positions`` (``_measure_into``, then the angle errors and the flags) into
    its rows of ``formations``."""
    start, end = constants.starts[team], constants.starts[team + 1]
    formation = team_formation(team, constants.starts, formations)
    flying = constants.flying[start:end]
    _measure_into(positions, flying, constants.neighbours[start:end], constants.reference_bearings[start:end], formation)
    angles, angle_errors, orientation_flags = formation.angles_deg, formation.angle_errors_deg, formation.orientation_flags
    neighbour_distances, beta_ref, d_ref, in_range = (
        formation.neighbour_distances,
        constants.beta_ref[team],
        constants.d_ref,
        True,
    )
    for agent in range(end - start):
        angle_errors[agent] = beta_ref - angles[agent]
        orientation_flags[agent] = angles[agent] > 0.0 and angles[agent] < 180.0
        for slot in range(neighbour_distances.shape[1]):
            in_range = in_range and (neighbour_distances[agent, slot] <= d_ref or not flying[agent])
    formations.range_flags[team] = in_range


@numba.njit(cache=True)
def _terms_and_ends(
    active: np.ndarray,
    constant_fields: Fields,
    formation_fields: Fields,
    latest_fields: Fields,
    step_counts: np.ndarray,
    reward_fields: Fields,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Count the step of each of the ``active`` teams, put their reward terms into the latest step's terms (each team's
    ``(terms, n)`` block of ``_reward_terms``, the blocks one after the other, flat; other teams' blocks are left as
    they are), and say which of them ended: terminated (the centroid within eta_g of the goal), truncated (T_s steps
    without that).

    :param step_counts: every team's steps since its reset (:attr:`~sb3_formation.env.stacked.Episodes.step_counts`),
        counted here
    :param reward_fields: the :class:`~sb3_formation.env.rewards.RewardConstants`' fields
    :return: ``(teams,)`` terminated and truncated (``False`` for the other teams)
    """
    constants, formations, latest = Constants(*constant_fields), Formations(*formation_fields), StepArrays(*latest_fields)
    rewards = RewardConstants(*reward_fields)
    starts, neighbours, terms = constants.starts, constants.neighbours, latest.terms
    previous_ways, ways, goal_distances = latest.previous_ways, latest.ways, latest.goal_distances
    previous_velocities, velocities = latest.previous_velocities, latest.velocities
    nearest_agent, nearest_obstacle = formations.nearest_agent_distances, formations.nearest_obstacle_gaps
    terminated, truncated = np.zeros(step_counts.shape[0], dtype=np.bool_), np.zeros(step_counts.shape[0], dtype=np.bool_)
    for team in active:
        start, end = starts[team], starts[team + 1]
        step_counts[team] += 1
        _reward_terms(
            step_counts[team],
            team_formation(team, starts, formations),
            (previous_ways[team], ways[team], goal_distances[team]),
            (previous_velocities[start:end], velocities[start:end]),
            neighbours[start:end],
            (nearest_agent[start:end], nearest_obstacle[start:end]),
            rewards,
            terms[_N_TERMS * start : _N_TERMS * end].reshape(_N_TERMS, end - start),
            constants.flying[start:end],
        )
        terminated[team] = goal_distances[team] <= rewards.eta_g
        truncated[team] = not terminated[team] and step_counts[team] >= rewards.max_steps
    return terminated, truncated


@numba.njit(cache=True)
def _observe_teams(
    active: np.ndarray,
    constant_fields: Fields,
    shape_fields: Fields,
    formation_fields: Fields,
    latest_fields: Fields,
    episode_fields: Fields,
    observed: np.ndarray,
    team_means: np.ndarray,
    accumulate: bool,
    sensing: Fields,
) -> None:  # pragma: no cover - compiled
    """The ``active`` teams' lidar scans (into the episodes' lidar), observations and info values (into the latest
    step's) and, with ``accumulate``, the step added to their episodes' running sums (``team_means``: every team's
    mean reward of the step).

    :param observed: ``(agents, e)`` what every agent's dynamics add to its observation
    :param sensing: what the agents observe from: positions and velocities ``(agents, 2)`` (m, m/s), the fields of
        their formations, and their lidars' errors: heading errors ``(agents,)`` (rad) that turn the rays, range errors
        ``(agents, rays)`` (shares of the range) and dropped beams ``(agents, rays)`` (empty arrays: none)
    """
    constants, shapes, formations = Constants(*constant_fields), Shapes(*shape_fields), Formations(*formation_fields)
    latest, episodes = StepArrays(*latest_fields), Episodes(*episode_fields)
    positions, velocities, sensed_fields, heading_errors, beam_noise, dropped = sensing
    sensed = Formations(*sensed_fields)
    for team in active:
        _scan(team, constants, shapes, latest.positions, episodes.lidar, heading_errors)
        if beam_noise.size or dropped.size:
            _add_beam_errors(team, constants, episodes.lidar, beam_noise, dropped)
        _fill_observations(team, constants, sensed, (positions, velocities), latest.observations, episodes, observed)
        _fill_info_values(team, constants, formations, latest)
        if accumulate:
            _add_step(team, constants, formations, latest, episodes, team_means[team])


@numba.njit(cache=True)
def _store_formations(
    active: np.ndarray, constant_fields: Fields, positions: np.ndarray, formation_fields: Fields
) -> None:  # pragma: no cover - compiled
    """The formations of the ``active`` teams at ``positions`` (every agent's rows) into ``formation_fields``."""
    constants, formations = Constants(*constant_fields), Formations(*formation_fields)
    for team in active:
        _store_formation(team, constants, positions[constants.starts[team] : constants.starts[team + 1]], formations)


@numba.njit(cache=True)
def _add_beam_errors(
    team: int, constants: Constants, lidar: np.ndarray, beam_noise: np.ndarray, dropped: np.ndarray
) -> None:  # pragma: no cover - compiled
    """A team's beams' errors on its rows of ``lidar`` (shares of the range): a dropped beam reads 1 (nothing seen)
    on both channels; a beam that saw something reads its range plus its error, within [0, 1]."""
    for row in range(constants.starts[team], constants.starts[team + 1]):
        for ray in range(lidar.shape[2]):
            if dropped.size and dropped[row, ray]:
                lidar[0, row, ray] = lidar[1, row, ray] = 1.0
            elif beam_noise.size:
                for channel in range(2):
                    if lidar[channel, row, ray] < 1.0:
                        lidar[channel, row, ray] = min(max(lidar[channel, row, ray] + beam_noise[row, ray], 0.0), 1.0)


@numba.njit(cache=True)
def _scan(
    team: int, constants: Constants, shapes: Shapes, positions: np.ndarray, lidar: np.ndarray, heading_errors: np.ndarray
) -> None:  # pragma: no cover - compiled
    """A team's ``Lidar.scan`` into its rows of ``lidar``: its agents' circles (the last ones) take their positions.
    With ``heading_errors`` (``(agents,)`` rad, empty: none) an agent's ray k looks along direction k turned by minus
    its error: what its lidar, read in the frame of its heading estimate, puts in reading k."""
    start, end = constants.starts[team], constants.starts[team + 1]
    n_circles = shapes.circle_counts[team]
    circles = shapes.circles[team, :n_circles]
    circles[n_circles - (end - start) :, :2] = positions[start:end]
    layout = LidarLayout(
        circles,
        shapes.visible[start:end, :n_circles],
        shapes.channels[team, :n_circles],
        shapes.walls[team, : shapes.wall_counts[team]],
    )
    ranges = lidar[:, start:end]
    geometry = (constants.agent_radius, constants.width, constants.height, constants.lidar_range)
    if heading_errors.size == 0:
        lidar_ranges(positions[start:end], constants.directions, layout, *geometry, ranges)
    else:
        directions = np.empty_like(constants.directions)
        for agent in range(end - start):
            cos, sin = math.cos(-heading_errors[start + agent]), math.sin(-heading_errors[start + agent])
            for ray in range(directions.shape[0]):
                x, y = constants.directions[ray, 0], constants.directions[ray, 1]
                directions[ray, 0], directions[ray, 1] = cos * x - sin * y, sin * x + cos * y
            own = LidarLayout(layout.circles, layout.visible[agent : agent + 1], layout.channels, layout.walls)
            origin, out = positions[start + agent : start + agent + 1], ranges[:, agent : agent + 1]
            lidar_ranges(origin, directions, own, *geometry, out)
    ranges /= constants.lidar_range


@numba.njit(cache=True)
def _fill_info_values(
    team: int, constants: Constants, formations: Formations, latest: StepArrays
) -> None:  # pragma: no cover - compiled
    """A team's agents' info values (:class:`InfoColumn`) into their rows of ``latest.info_values``."""
    start, end = constants.starts[team], constants.starts[team + 1]
    n_agents, values, terms = end - start, latest.info_values, latest.terms
    centroid_distances, goal_distance = formations.centroid_distances, latest.goal_distances[team]
    angle, bearing, distance = agent_errors(
        formations.angle_errors_deg[start:end],
        formations.bearing_errors[start:end],
        formations.neighbour_distances[start:end],
        constants.d_ref,
    )
    for agent in range(n_agents):
        row = start + agent
        values[row, InfoColumn.ANGLE_ERROR_DEG] = angle[agent]
        values[row, InfoColumn.BEARING_ERROR] = bearing[agent]
        values[row, InfoColumn.NEIGHBOUR_DISTANCE_ERROR] = distance[agent]
        values[row, InfoColumn.CENTROID_DISTANCE] = centroid_distances[row]
        values[row, InfoColumn.GOAL_DISTANCE] = goal_distance
        for term in range(_N_TERMS):
            values[row, InfoColumn.FIRST_TERM + term] = terms[_N_TERMS * start + term * n_agents + agent]


@numba.njit(cache=True)
def _add_step(
    team: int, constants: Constants, formations: Formations, latest: StepArrays, episodes: Episodes, team_mean: float
) -> None:  # pragma: no cover - compiled
    """Add a team's step to its episode's running sums: from its flying agents' info values, agent by agent, each over
    their number (as a team's infos would be summed)."""
    start, end = constants.starts[team], constants.starts[team + 1]
    values, contacts, flying = latest.info_values, latest.contacts, constants.flying
    errors, collisions, term_sums = episodes.errors, episodes.collisions, episodes.term_sums
    neighbour_distances, d_comm = formations.neighbour_distances, constants.d_comm
    episodes.returns[team] += team_mean
    comm_exceeded, n_agents = False, flying[start:end].sum()
    for row in range(start, end):
        if not flying[row]:  # a failed agent's errors and contacts are not the team's
            continue
        errors[team, 0] += values[row, InfoColumn.ANGLE_ERROR_DEG] / n_agents
        errors[team, 1] += values[row, InfoColumn.BEARING_ERROR] / n_agents
        errors[team, 2] += values[row, InfoColumn.NEIGHBOUR_DISTANCE_ERROR] / n_agents
        collisions[team, 0] += contacts[row, ContactColumn.OBSTACLES]
        collisions[team, 1] += contacts[row, ContactColumn.AGENTS]
        collisions[team, 2] += contacts[row, ContactColumn.RAMMED]
        for term in range(_N_TERMS):
            term_sums[team, term] += values[row, InfoColumn.FIRST_TERM + term] / n_agents
        for slot in range(neighbour_distances.shape[1]):
            comm_exceeded = comm_exceeded or neighbour_distances[row, slot] > d_comm
    episodes.comm_exceeded[team] += comm_exceeded
