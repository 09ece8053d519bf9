"""Every team's numbers, stacked: the few named structures that the engine keeps and its compiled kernels take.

Agents are stacked team after team (team t holds rows ``starts[t]:starts[t + 1]``, agent 0 first). Each structure is a
``NamedTuple`` of numpy arrays and numbers that compiled code reads by field name, so a kernel takes a handful of
structures instead of dozens of arrays. The structures differ by when their arrays change:

- :class:`Constants`: fixed for the engine's life, but for a team's ring while an agent of it has failed;
- :class:`Shapes`: every team's obstacles and walls, loaded at the team's reset;
- :class:`Formations`: every team's formation, measured in place after each step or reset;
- :class:`StepArrays`: what a step makes anew (the arrays the engine returns among them) and what it compares with;
- :class:`Episodes`: every team's episode so far, written in place.

The engine hands a structure to a kernel as the plain tuple of its fields, ``tuple(structure)``, and the kernel names
the fields again at no cost (``Constants(*fields)``): numba types its arguments anew at every call, and it types a
plain tuple of ten arrays in a third of the time it takes for a ``NamedTuple`` (whose type carries its class and field
names), a microsecond per structure and call that a step of a single team would notice.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numba
import numpy as np

from sb3_formation.env.geometry import FormationState

#: a structure's fields as a plain tuple, as the kernels take them (see the module docstring)
Fields = tuple[Any, ...]


class Constants(NamedTuple):
    """What stays fixed for an engine's life: the teams' rows, the agents' neighbours and the task's constants. The
    ring of a team whose agent failed (:meth:`~sb3_formation.env.engine.FormationEngine.fail`) is that of its flying
    agents until its next reset: their neighbours, reference bearings and beta^ref."""

    starts: np.ndarray  #: ``(teams + 1,)`` int64: the first row of each team, then the number of rows
    neighbours: np.ndarray  #: ``(agents, 2)`` int64: each agent's preceding and succeeding neighbour, within its team
    reference_bearings: np.ndarray  #: ``(agents, 2, 2)`` reference bearings g_j^{i,ref}
    beta_ref: np.ndarray  #: ``(teams,)`` reference angle beta^ref (deg) of each team's ring
    flying: np.ndarray  #: ``(agents,)`` bool: the agent's motors run (it has not failed)
    directions: np.ndarray  #: ``(rays, 2)`` unit directions of the lidar's rays
    d_ref: float  #: reference neighbour distance d^ref (m)
    d_comm: float  #: communication range d_comm (m)
    eta_c: float  #: centroid distance eta_c (m)
    agent_radius: float  #: R_a (m)
    width: float  #: world width (m)
    height: float  #: world height (m)
    lidar_range: float  #: lidar range (m)
    observe_reference: bool  #: an observation ends with the agent's reference bearings


class Shapes(NamedTuple):
    """Every team's obstacles and walls, as its lidar and the nearest gaps read them, padded to the most of any team.

    The circles of a team are its :class:`~sb3_formation.env.sensors.LidarLayout`'s: its obstacles, then its agents
    (whose centres each scan sets).
    """

    circles: np.ndarray  #: ``(teams, m, 3)`` x, y, radius (m)
    visible: np.ndarray  #: ``(agents, m)`` bool: the circles each agent's lidar may see
    channels: np.ndarray  #: ``(teams, m)`` int64: the lidar channel of each circle
    circle_counts: np.ndarray  #: ``(teams,)`` int64: each team's circles (its obstacles and its agents)
    walls: np.ndarray  #: ``(teams, w, 5)`` walls x0, y0, x1, y1, thickness (m)
    wall_counts: np.ndarray  #: ``(teams,)`` int64: each team's walls

    @classmethod
    def empty(cls, n_teams: int, n_slots: int) -> Shapes:
        """No circle and no wall for any team (before its first reset)."""
        return cls(
            circles=np.zeros((n_teams, 0, 3)),
            visible=np.zeros((n_slots, 0), dtype=bool),
            channels=np.zeros((n_teams, 0), dtype=np.int64),
            circle_counts=np.zeros(n_teams, dtype=np.int64),
            walls=np.zeros((n_teams, 0, 5)),
            wall_counts=np.zeros(n_teams, dtype=np.int64),
        )


class Formations(NamedTuple):
    """Every team's formation now: the fields of :class:`~sb3_formation.env.geometry.FormationState`, stacked, and
    every agent's nearest gaps (:func:`~sb3_formation.env.rewards.nearest_gaps`)."""

    centroids: np.ndarray  #: ``(teams, 2)`` centroid p^c (m)
    centroid_distances: np.ndarray  #: ``(agents,)`` |p^i - p^c| (m)
    neighbour_offsets: np.ndarray  #: ``(agents, 2, 2)`` p^j - p^i (m)
    neighbour_distances: np.ndarray  #: ``(agents, 2)`` |p^j - p^i| (m)
    bearings: np.ndarray  #: ``(agents, 2, 2)`` unit bearings g_j^i
    angles_deg: np.ndarray  #: ``(agents,)`` beta^i (deg)
    angle_errors_deg: np.ndarray  #: ``(agents,)`` signed beta^ref - beta^i (deg)
    bearing_errors: np.ndarray  #: ``(agents, 2)`` |g_j^{i,ref} - g_j^i|
    orientation_flags: np.ndarray  #: ``(agents,)`` bool: beta^i in (0, 180)
    range_flags: np.ndarray  #: ``(teams,)`` bool: every agent within d_ref of each of its neighbours
    nearest_agent_distances: np.ndarray  #: ``(agents,)`` centre distance (m) to the nearest other agent
    nearest_obstacle_gaps: np.ndarray  #: ``(agents,)`` surface gap (m) to the nearest obstacle, wall or border

    @classmethod
    def zeros(cls, n_teams: int, n_slots: int) -> Formations:
        """Every team's formation before its first reset: zeros."""
        return cls(
            centroids=np.zeros((n_teams, 2)),
            centroid_distances=np.zeros(n_slots),
            neighbour_offsets=np.zeros((n_slots, 2, 2)),
            neighbour_distances=np.zeros((n_slots, 2)),
            bearings=np.zeros((n_slots, 2, 2)),
            angles_deg=np.zeros(n_slots),
            angle_errors_deg=np.zeros(n_slots),
            bearing_errors=np.zeros((n_slots, 2)),
            orientation_flags=np.zeros(n_slots, dtype=bool),
            range_flags=np.zeros(n_teams, dtype=bool),
            nearest_agent_distances=np.zeros(n_slots),
            nearest_obstacle_gaps=np.zeros(n_slots),
        )


class StepArrays(NamedTuple):
    """What the latest step (or reset) made: every agent's and team's values after it, and the values before it that
    the reward compares with.

    A step makes every array anew. The engine returns the positions, velocities, contacts, observations and info
    values, and never writes them again: a reset copies them before it writes its team's rows.
    """

    positions: np.ndarray  #: ``(agents, 2)`` (m)
    velocities: np.ndarray  #: ``(agents, 2)`` (m/s)
    previous_velocities: np.ndarray  #: ``(agents, 2)`` the velocities before the step (m/s)
    contacts: (
        np.ndarray
    )  #: ``(agents, 3)`` int64: other agents, obstacles or walls, and the movers that ran into it (ContactColumn)
    observations: np.ndarray  #: ``(agents, dim)`` float32
    info_values: np.ndarray  #: ``(agents, INFO_VALUES)`` (:class:`~sb3_formation.env.engine.InfoColumn`)
    terms: np.ndarray  #: ``(terms * agents,)`` reward terms before coefficients: each team's ``(terms, n)`` block, flat
    goal_distances: np.ndarray  #: ``(teams,)`` centroid-goal distance (m)
    ways: np.ndarray  #: ``(teams,)`` the way (m) to the goal whose decrease the goal term rewards
    previous_ways: np.ndarray  #: ``(teams,)`` the ways before the step (m)

    @classmethod
    def zeros(cls, n_teams: int, n_slots: int, dim: int, n_values: int, n_terms: int) -> StepArrays:
        """Every agent and team before its first reset: zeros.

        :param dim: the size of an observation
        :param n_values: the info values of an agent
        :param n_terms: the reward terms
        """
        return cls(
            positions=np.zeros((n_slots, 2)),
            velocities=np.zeros((n_slots, 2)),
            previous_velocities=np.zeros((n_slots, 2)),
            contacts=np.zeros((n_slots, 3), dtype=np.int64),
            observations=np.zeros((n_slots, dim), dtype=np.float32),
            info_values=np.zeros((n_slots, n_values)),
            terms=np.zeros(n_terms * n_slots),
            goal_distances=np.zeros(n_teams),
            ways=np.zeros(n_teams),
            previous_ways=np.zeros(n_teams),
        )


class Episodes(NamedTuple):
    """Every team's episode so far (written in place): its goal and steps, what its agents remember of the last step,
    their lidar readings, and the running sums of its summary (:func:`~sb3_formation.env.episodes.episode_summary`)."""

    goals: np.ndarray  #: ``(teams, 2)`` (m)
    step_counts: np.ndarray  #: ``(teams,)`` int64: steps since the reset
    previous_offsets: np.ndarray  #: ``(teams, 2)`` c_g^v = p^g - p^c one step earlier (m)
    previous_actions: np.ndarray  #: ``(agents, 2)`` the actions of the last step
    previous_rewards: np.ndarray  #: ``(agents,)`` the rewards of the last step that agents observe
    lidar: np.ndarray  #: ``(2, agents, rays)`` readings of the obstacle and agent channels, in [0, 1]
    returns: np.ndarray  #: ``(teams,)`` sum over steps of the team's mean reward
    errors: np.ndarray  #: ``(teams, 3)`` sums over steps of the angle, bearing and neighbour-distance errors over n
    #: ``(teams, 3)`` int64: obstacle, then agent contacts, then the obstacle contacts where a moving obstacle ran into
    #: the agent, summed over agents and steps
    collisions: np.ndarray
    term_sums: np.ndarray  #: ``(teams, terms)`` sums over steps of every reward term over n
    comm_exceeded: np.ndarray  #: ``(teams,)`` int64: steps with a neighbour beyond d_comm

    @classmethod
    def zeros(cls, n_teams: int, n_slots: int, n_rays: int, n_terms: int) -> Episodes:
        """Every team before its first reset: zeros.

        :param n_rays: the rays of a lidar
        :param n_terms: the reward terms
        """
        return cls(
            goals=np.zeros((n_teams, 2)),
            step_counts=np.zeros(n_teams, dtype=np.int64),
            previous_offsets=np.zeros((n_teams, 2)),
            previous_actions=np.zeros((n_slots, 2)),
            previous_rewards=np.zeros(n_slots),
            lidar=np.zeros((2, n_slots, n_rays)),
            returns=np.zeros(n_teams),
            errors=np.zeros((n_teams, 3)),
            collisions=np.zeros((n_teams, 3), dtype=np.int64),
            term_sums=np.zeros((n_teams, n_terms)),
            comm_exceeded=np.zeros(n_teams, dtype=np.int64),
        )


class StepTeams(NamedTuple):
    """The teams a step moves: every team in an episode."""

    active: np.ndarray  #: their indices (int64)
    teams: list[int]  #: the same, as a list
    pick: slice | np.ndarray  #: their entries of a per-team array (``slice(None)``: every team)
    rows: np.ndarray | None  #: ``(agents,)`` bool: their agents' rows (``None``: every agent)
    everyone: bool  #: every team steps

    def merged(self, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """A new array: ``new`` (one row for each of their agents, in order) in their agents' rows, ``old`` elsewhere."""
        if self.rows is None:
            return new
        merged: np.ndarray = old.copy()
        merged[self.rows] = new
        return merged

    def write(self, target: np.ndarray, values: np.ndarray) -> None:
        """Write their agents' rows of ``values`` (a row for every agent) into ``target``'s."""
        if self.rows is None:
            target[...] = values
        else:
            target[self.rows] = values[self.rows]


def widened(array: np.ndarray, size: int) -> np.ndarray:
    """``array``, or a copy with its second axis grown to ``size`` (the new entries zero)."""
    if array.shape[1] >= size:
        return array
    grown = np.zeros((array.shape[0], size, *array.shape[2:]), dtype=array.dtype)
    grown[:, : array.shape[1]] = array
    return grown


@numba.njit(cache=True)
def team_formation(team: int, starts: np.ndarray, formations: Formations) -> FormationState:  # pragma: no cover - compiled
    """A team's formation: views of its rows of ``formations``."""
    start, end = starts[team], starts[team + 1]
    return FormationState(
        formations.centroids[team],
        formations.centroid_distances[start:end],
        formations.neighbour_offsets[start:end],
        formations.neighbour_distances[start:end],
        formations.bearings[start:end],
        formations.angles_deg[start:end],
        formations.angle_errors_deg[start:end],
        formations.bearing_errors[start:end],
        formations.orientation_flags[start:end],
        formations.range_flags[team],
    )
