"""Formation geometry: ring neighbours, bearings, angles and errors. Pure numpy functions.

Conventions (``docs/design.md`` "Ring topology"): agent indices are 0-based (agent 0 is the thesis's agent 1);
agent i's designated neighbours are ``(i - 1) % n`` (preceding) and ``(i + 1) % n`` (succeeding); bearings are unit
vectors in the world frame; angles are in degrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numba
import numpy as np

#: Below this distance (m) two points are taken as coincident and their bearing is the zero vector.
COINCIDENT_DISTANCE = 1e-12


def ring_neighbours(n_agents: int) -> np.ndarray:
    """Designated neighbours N_2^i of every agent on the ring.

    :param n_agents: team size n (>= 3)
    :return: ``(n, 2)`` int array; column 0 is the preceding agent i - 1, column 1 the succeeding agent i + 1 (mod n)
    """
    index = np.arange(n_agents)
    return np.stack([(index - 1) % n_agents, (index + 1) % n_agents], axis=1)


def ring_rows(team_sizes: Sequence[int]) -> np.ndarray:
    """Ring neighbours of every row of teams stacked one after the other (the order of the policy seam's rows and of a
    VecEnv's slots: team 0's agents, agent 0 first, then team 1's, ...).

    :param team_sizes: each team's size n_j (>= 3), in row order
    :return: ``(sum n_j, 2)`` int array: the rows of each row's preceding and succeeding neighbour in its team
    """
    firsts = np.cumsum([0, *team_sizes])[:-1]
    return np.concatenate([ring_neighbours(int(n)) + first for n, first in zip(team_sizes, firsts)] or [np.zeros((0, 2), int)])


class FlyingRing(NamedTuple):
    """The ring that a team's agents that still fly close without the failed ones (``docs/disturbances.md``, "Agents
    that fail"): the flying agents in their order, each linked to the flying agents before and after it."""

    neighbours: (
        np.ndarray
    )  #: ``(n, 2)`` int: each agent's preceding and succeeding neighbour (a failed agent: its own old ones)
    places: np.ndarray  #: ``(n,)`` int: each flying agent's place on the ring of the flying agents (a failed agent: 0)
    size: int  #: the flying agents, the ring's size (>= 3)


def flying_ring(flying: np.ndarray) -> FlyingRing:
    """The ring of a team's flying agents: agent i that flies takes place k (its rank among the flying agents) on the
    ring of ``size`` agents and is linked to the flying agents of places k - 1 and k + 1 (mod ``size``); with every
    agent flying this is :func:`ring_neighbours`.

    :param flying: ``(n,)`` bool: the agents whose motors run
    :raises ValueError: fewer than 3 agents fly (no ring)
    """
    flying = np.asarray(flying, dtype=bool)
    n_agents, order = len(flying), np.flatnonzero(flying)
    size = len(order)
    if size < 3:
        raise ValueError(f"a ring needs at least 3 flying agents, {size} of {n_agents} fly")
    neighbours, places = ring_neighbours(n_agents), np.zeros(n_agents, dtype=np.int64)
    places[order] = np.arange(size)
    neighbours[order] = order[ring_neighbours(size)]
    return FlyingRing(neighbours, places, size)


def flying_rows(flying: np.ndarray, n_agents: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`flying_ring` of rows of whole teams of ``n_agents`` (row k: agent ``k % n`` of team ``k // n``).

    :param flying: ``(k,)`` bool: the rows whose agents fly
    :return: ``(k, 2)`` each row's place on its team's ring and the ring's size, and ``(k, 2)`` the rows of its
        preceding and succeeding neighbours
    """
    places, neighbours = np.empty((len(flying), 2), dtype=np.int64), np.empty((len(flying), 2), dtype=np.int64)
    for first in range(0, len(flying), n_agents):
        ring = flying_ring(flying[first : first + n_agents])
        places[first : first + n_agents] = np.stack([ring.places, np.full(n_agents, ring.size)], axis=1)
        neighbours[first : first + n_agents] = first + ring.neighbours
    return places, neighbours


def interior_angle_deg(n_agents: int) -> float:
    """Interior angle (deg) of the regular n-gon: the reference angle beta^ref."""
    return (n_agents - 2) * 180.0 / n_agents


def edge_angles_deg(n_agents: int) -> np.ndarray:
    """Angle phi_i (deg) of the reference bearing from vertex i to vertex i + 1: 180/n + i * 360/n (0-based i)."""
    return 180.0 / n_agents + np.arange(n_agents) * 360.0 / n_agents


def reference_bearings(n_agents: int) -> np.ndarray:
    """Reference unit bearings g_j^{i,ref} of the anti-clockwise regular n-gon (Table 5.2, normalised, for n = 6).

    :param n_agents: team size n
    :return: ``(n, 2, 2)`` array: ``[i, 0]`` towards the preceding neighbour, ``[i, 1]`` towards the succeeding one
    """
    phi = np.deg2rad(edge_angles_deg(n_agents))
    to_next = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # from i to i + 1
    to_previous = -np.roll(to_next, 1, axis=0)  # from i to i - 1 is minus (from i - 1 to i)
    return np.stack([to_previous, to_next], axis=1)


def reference_polygon(n_agents: int, circumradius: float) -> np.ndarray:
    """Vertices of the reference n-gon around the origin, vertex i at angle i * 360/n - 90 deg (agent 0 at the bottom).

    Traversed 0 -> 1 -> ... anti-clockwise, so the bearing from vertex i to i + 1 is :func:`edge_angles_deg`.

    :param n_agents: team size n
    :param circumradius: distance (m) of every vertex from the centre
    :return: ``(n, 2)`` positions (m) relative to the centroid
    """
    theta = np.deg2rad(np.arange(n_agents) * 360.0 / n_agents - 90.0)
    return circumradius * np.stack([np.cos(theta), np.sin(theta)], axis=1)


class FormationState(NamedTuple):
    """Everything the observation, the reward and ``info`` need to know about the team's shape, at one instant.

    Shapes: n agents; the neighbour axis is (preceding, succeeding).
    """

    centroid: np.ndarray  #: (2,) centroid p^c (m), eq. 20
    centroid_distances: np.ndarray  #: (n,) |p^i - p^c| (m)
    neighbour_offsets: np.ndarray  #: (n, 2, 2) p^j - p^i (m)
    neighbour_distances: np.ndarray  #: (n, 2) |p^j - p^i| (m)
    bearings: np.ndarray  #: (n, 2, 2) unit bearings g_j^i, eq. 16
    angles_deg: np.ndarray  #: (n,) beta^i (deg)
    angle_errors_deg: np.ndarray  #: (n,) signed beta^ref - beta^i (deg)
    bearing_errors: np.ndarray  #: (n, 2) |g_j^{i,ref} - g_j^i|
    orientation_flags: np.ndarray  #: (n,) bool: beta^i in (0, 180)
    range_flag: bool  #: every agent within d_ref of each of its neighbours


def measure_formation(
    positions: np.ndarray,
    neighbours: np.ndarray,
    reference: np.ndarray,
    beta_ref_deg: float,
    d_ref: float,
    flying: np.ndarray | None = None,
) -> FormationState:
    """Measure the team's formation.

    :param positions: ``(n, 2)`` agent positions (m)
    :param neighbours: ``(n, 2)`` neighbour indices from :func:`ring_neighbours` (or :func:`flying_ring`)
    :param reference: ``(n, 2, 2)`` reference bearings from :func:`reference_bearings`
    :param beta_ref_deg: reference angle beta^ref (deg)
    :param d_ref: reference neighbour distance d^ref (m)
    :param flying: ``(n,)`` bool: the agents that fly, whose centroid and range flag count (``None``: every agent)
    """
    n_agents, n_neighbours = len(positions), neighbours.shape[1]
    measured = FormationState(
        centroid=np.empty(2),
        centroid_distances=np.empty(n_agents),
        neighbour_offsets=np.empty((n_agents, n_neighbours, 2)),
        neighbour_distances=np.empty((n_agents, n_neighbours)),
        bearings=np.empty((n_agents, n_neighbours, 2)),
        angles_deg=np.empty(n_agents),
        angle_errors_deg=np.empty(n_agents),
        bearing_errors=np.empty((n_agents, n_neighbours)),
        orientation_flags=np.empty(n_agents, dtype=bool),
        range_flag=False,
    )
    flying = np.ones(n_agents, dtype=bool) if flying is None else np.asarray(flying, dtype=bool)
    _measure_into(np.ascontiguousarray(positions, dtype=np.float64), flying, neighbours, reference, measured)
    angles, distances = measured.angles_deg, measured.neighbour_distances
    return measured._replace(
        angle_errors_deg=beta_ref_deg - angles,
        orientation_flags=(angles > 0.0) & (angles < 180.0),
        range_flag=bool((distances[flying] <= d_ref).all()),
    )


@numba.njit(cache=True)
def agent_errors(
    angle_errors_deg: np.ndarray, bearing_errors: np.ndarray, neighbour_distances: np.ndarray, d_ref: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Per agent, what the infos and episode means report: the absolute angle error (deg), the mean bearing error over
    its two neighbours, and the mean of their distance errors beyond d^ref (m).

    :param angle_errors_deg: ``(n,)`` signed angle errors (:attr:`FormationState.angle_errors_deg`)
    :param bearing_errors: ``(n, 2)`` bearing errors
    :param neighbour_distances: ``(n, 2)`` neighbour distances (m)
    :param d_ref: reference neighbour distance d^ref (m)
    """
    n_agents = angle_errors_deg.shape[0]
    angle, bearing, distance = np.empty(n_agents), np.empty(n_agents), np.empty(n_agents)
    for agent in range(n_agents):
        angle[agent] = abs(angle_errors_deg[agent])
        bearing[agent] = 0.5 * (bearing_errors[agent, 0] + bearing_errors[agent, 1])
        beyond = max(neighbour_distances[agent, 0] - d_ref, 0.0) + max(neighbour_distances[agent, 1] - d_ref, 0.0)
        distance[agent] = 0.5 * beyond
    return angle, bearing, distance


@numba.njit(cache=True)
def _measure_into(
    positions: np.ndarray, flying: np.ndarray, neighbours: np.ndarray, reference: np.ndarray, out: FormationState
) -> None:  # pragma: no cover - compiled
    """Compiled core of :func:`measure_formation`: the centroid (eq. 20) of the ``flying`` agents, distances, eq. 16
    bearings, beta^i and the bearing errors, in one loop, into ``out``'s arrays (its angle errors, flags and range flag
    are left as they are). The centroid sums the flying agents in order: with every agent flying, numba's sum."""
    n_agents, n_neighbours = positions.shape[0], neighbours.shape[1]
    centroid, centroid_distances, offsets, distances = (
        out.centroid,
        out.centroid_distances,
        out.neighbour_offsets,
        out.neighbour_distances,
    )
    bearings, angles, bearing_errors = out.bearings, out.angles_deg, out.bearing_errors
    x_sum, y_sum, count = 0.0, 0.0, 0
    for agent in range(n_agents):
        if flying[agent]:
            x_sum, y_sum, count = x_sum + positions[agent, 0], y_sum + positions[agent, 1], count + 1
    centroid[0], centroid[1] = x_sum / count, y_sum / count
    for agent in range(n_agents):
        centroid_distances[agent] = math.hypot(positions[agent, 0] - centroid[0], positions[agent, 1] - centroid[1])
        for slot in range(n_neighbours):
            dx = positions[neighbours[agent, slot], 0] - positions[agent, 0]
            dy = positions[neighbours[agent, slot], 1] - positions[agent, 1]
            distance = math.hypot(dx, dy)
            offsets[agent, slot, 0], offsets[agent, slot, 1] = dx, dy
            distances[agent, slot] = distance
            if distance > COINCIDENT_DISTANCE:
                bearings[agent, slot, 0], bearings[agent, slot, 1] = dx / distance, dy / distance
            else:  # coincident: no bearing
                bearings[agent, slot, 0], bearings[agent, slot, 1] = 0.0, 0.0
            bearing_errors[agent, slot] = math.hypot(
                reference[agent, slot, 0] - bearings[agent, slot, 0], reference[agent, slot, 1] - bearings[agent, slot, 1]
            )
        to_previous = math.degrees(math.atan2(bearings[agent, 0, 1], bearings[agent, 0, 0]))
        to_next = math.degrees(math.atan2(bearings[agent, 1, 1], bearings[agent, 1, 0]))
        angles[agent] = (to_previous - to_next) % 360.0
