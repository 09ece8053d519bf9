"""How actions move agents: the thesis's holonomic point (eq. 19) or a unicycle, chosen once from ``config.dynamics``.

A :class:`Dynamics` turns a step's actions into what each team's :class:`~sb3_formation.env.world.World` is told (a
velocity, or a forward speed and a turn rate), lets the worlds move their agents, and reads their positions and
velocities back (steps 1 to 3 of a step in ``docs/design.md``). It keeps the state its agents have beyond a point's
(a unicycle's heading and forward speed) and writes what of it an agent observes.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import NamedTuple

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.stacked import StepTeams
from sb3_formation.env.world import World, clamp_speed, split_state

#: what a world's step returns: ``None`` when no agent touched anything, else the agent and obstacle contact counts
Touched = tuple[np.ndarray, np.ndarray] | None


class Moved(NamedTuple):
    """The stepped teams' agents after the physics of a step."""

    positions: np.ndarray  #: ``(k, 2)`` (m), the stepped teams' agents one team after the other
    velocities: np.ndarray  #: ``(k, 2)`` (m/s)
    touched: list[Touched]  #: each stepped team's contacts (:meth:`World.advance`), in the order of the teams


class Dynamics(ABC):
    """How actions move the agents of an engine's teams (see the module docstring).

    :param config: the task configuration (the teams differ in ``n_agents`` only)
    :param starts: the first row of each team, then the number of rows
    """

    def __init__(self, config: FormationConfig, starts: np.ndarray) -> None:
        self.config = config
        self.starts = starts

    def velocity_changes(self, actions: np.ndarray) -> np.ndarray:
        """Eq. 19: the velocity change (m/s) of each action's force a * F_max over a step, F / m * dt."""
        config = self.config
        changes: np.ndarray = (actions * config.force_max) * (config.dt / config.agent_mass)
        return changes

    @abstractmethod
    def move(self, actions: np.ndarray, velocities: np.ndarray, worlds: list[World], stepped: StepTeams) -> Moved:
        """Move the stepped teams' agents over a step.

        :param actions: ``(agents, 2)`` actions within [-1, 1], a row for every agent
        :param velocities: ``(agents, 2)`` velocities (m/s) before the step
        :param worlds: every team's world
        :param stepped: the teams to move
        """

    @abstractmethod
    def reset(self, rows: slice, world: World) -> None:
        """Start the episode of a team (its agents' ``rows``) placed in ``world``."""

    @abstractmethod
    def observe(self, observations: np.ndarray, rows: slice | np.ndarray) -> None:
        """Write what agents ``rows`` observe of their state beyond a point's into their rows of ``observations``."""

    @abstractmethod
    def headings_of(self, rows: slice) -> np.ndarray | None:
        """The headings (rad) of agents ``rows``, or ``None`` for agents without one."""


class HolonomicDynamics(Dynamics):
    """The thesis's point (eq. 19): the action is a force in the world frame; v <- v + F / m * dt, clamped to v_max."""

    def move(self, actions: np.ndarray, velocities: np.ndarray, worlds: list[World], stepped: StepTeams) -> Moved:
        v_max = self.config.v_max
        commanded, starts = clamp_speed(velocities + self.velocity_changes(actions), v_max), self.starts
        touched = [worlds[team].advance(commanded[starts[team] : starts[team + 1]]) for team in stepped.teams]
        positions, moved = split_state(np.concatenate([worlds[team].agent_states for team in stepped.teams]), v_max)
        return Moved(positions, moved, touched)

    def reset(self, rows: slice, world: World) -> None:
        """A point keeps no state beyond its position and velocity."""

    def observe(self, observations: np.ndarray, rows: slice | np.ndarray) -> None:
        """A point's observation is Table 3.1's."""

    def headings_of(self, rows: slice) -> np.ndarray | None:
        return None


class UnicycleDynamics(Dynamics):
    """A unicycle (:meth:`World.drive`): the action's first entry is a forward force along the heading, its second a
    turn rate as a share of ``max_turn_rate``. Keeps every agent's heading and forward speed; an agent observes the
    cosine and sine of its heading."""

    def __init__(self, config: FormationConfig, starts: np.ndarray) -> None:
        super().__init__(config, starts)
        #: every agent's heading (rad, anti-clockwise from +x) and forward speed (m/s)
        self.headings, self.forward_speeds = np.zeros(int(starts[-1])), np.zeros(int(starts[-1]))
        #: the heading's first column (cos) of an observation; its sine follows
        self.heading_column = observation_layout(observation_fields(config))["heading"].start

    def move(self, actions: np.ndarray, velocities: np.ndarray, worlds: list[World], stepped: StepTeams) -> Moved:
        v_max = self.config.v_max
        forward = np.clip(self.forward_speeds + self.velocity_changes(actions)[:, 0], -v_max, v_max)
        turns = actions[:, 1] * self.config.max_turn_rate
        teams, starts = stepped.teams, self.starts
        touched = [
            worlds[team].drive(forward[starts[team] : starts[team + 1]], turns[starts[team] : starts[team + 1]])
            for team in teams
        ]
        positions = np.concatenate([worlds[team].agent_states[:, :2] for team in teams])
        headings = np.concatenate([worlds[team].headings for team in teams])
        speeds = np.concatenate([worlds[team].forward_speeds for team in teams])
        self.headings = stepped.merged(self.headings, headings)
        self.forward_speeds = stepped.merged(self.forward_speeds, speeds)
        return Moved(positions, speeds[:, None] * np.stack([np.cos(headings), np.sin(headings)], axis=1), touched)

    def reset(self, rows: slice, world: World) -> None:
        self.headings, self.forward_speeds = self.headings.copy(), self.forward_speeds.copy()
        self.headings[rows], self.forward_speeds[rows] = world.headings, 0.0

    def observe(self, observations: np.ndarray, rows: slice | np.ndarray) -> None:
        column = self.heading_column
        observations[rows, column] = np.cos(self.headings[rows])
        observations[rows, column + 1] = np.sin(self.headings[rows])

    def headings_of(self, rows: slice) -> np.ndarray | None:
        return self.headings[rows]


#: ``FormationConfig.dynamics`` -> its class
DYNAMICS_CLASSES: dict[str, type[Dynamics]] = {"holonomic": HolonomicDynamics, "unicycle": UnicycleDynamics}
