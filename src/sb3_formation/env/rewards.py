"""Reward terms of eqs 21-42 as pure functions of numpy arrays, and their weighted, clipped sum.

Each term is returned *before* its coefficient, one value per agent. Chapter 4 (eq. 26) and chapter 5 (eq. 42) are
the same weighted sum with different coefficients (:data:`sb3_formation.env.config.TASKS`); chapter 4's ``ref`` term
(eq. 22) is the ``dist`` term (eq. 36) with m_ref in place of m_dist. With ``team_reward`` every agent receives the
team average of each per-agent term and the team collision term (eqs 27-32).

The functions are numba-compiled: a step evaluates them for a handful of agents, where numpy's per-call overhead
would dominate. They take and return plain numpy arrays and can be called from Python like numpy functions.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from sb3_formation.env.config import REWARD_TERMS, FormationConfig
from sb3_formation.env.geometry import FormationState
from sb3_formation.env.shapes import circle_gap, shape_gaps

#: A velocity slower than this (m/s) has no direction: the move and velocity terms are 0 for it (``docs/design.md`` "Rewards").
STILL_SPEED = 1e-6

#: Row of each term in the ``(len(REWARD_TERMS), n)`` array returned by :func:`reward_terms`.
TERM_ROW: dict[str, int] = {name: row for row, name in enumerate(REWARD_TERMS)}
_TIME, _ANGLE, _BEARING, _DIST, _CENTROID, _GOAL, _MOVE, _VELOCITY, _COLL = (TERM_ROW[name] for name in REWARD_TERMS)
_N_TERMS = len(REWARD_TERMS)


@numba.njit(cache=True)
def angle_between(first: np.ndarray, second: np.ndarray) -> float:  # pragma: no cover - compiled
    """Angle (rad, in [0, pi]) between two 2-D vectors; 0 if either is slower than :data:`STILL_SPEED`."""
    if math.hypot(first[0], first[1]) <= STILL_SPEED or math.hypot(second[0], second[1]) <= STILL_SPEED:
        return 0.0
    cross = first[0] * second[1] - first[1] * second[0]
    dot = first[0] * second[0] + first[1] * second[1]
    return abs(math.atan2(cross, dot))


@numba.njit(cache=True)
def time_term(step: int, max_steps: int, r_late: float) -> float:  # pragma: no cover - compiled
    """Eq. 33: r_late on the step that reaches T_s (``step`` = t + 1 == ``max_steps``), else 0."""
    return r_late if step == max_steps else 0.0


@numba.njit(cache=True)
def angle_term(angle_error_deg: float, m_ang_deg: float) -> float:  # pragma: no cover - compiled
    """Eqs 21 / 34: -|beta^ref - beta^i| / m_ang (both in degrees)."""
    return -abs(angle_error_deg) / m_ang_deg


@numba.njit(cache=True)
def bearing_term(bearing_errors: np.ndarray) -> float:  # pragma: no cover - compiled
    """Eq. 35: -0.5 / n(N_2^i) * sum_j |g_j^{i,ref} - g_j^i|, given the norms |g_ref - g| to the neighbours."""
    term: float = -0.5 * bearing_errors.sum() / bearing_errors.size
    return term


@numba.njit(cache=True)
def distance_term(neighbour_distances: np.ndarray, d_ref: float, m_dist: float) -> float:  # pragma: no cover
    """Eqs 22 / 36: -1 / n(N^i) * sum_j max(d_j^i - d^ref, 0) / m_dist (distances in m)."""
    term: float = -np.maximum(neighbour_distances - d_ref, 0.0).sum() / neighbour_distances.size / m_dist
    return term


@numba.njit(cache=True)
def centroid_term(centroid_distance: float, eta_c: float, r_c: float) -> float:  # pragma: no cover - compiled
    """Eq. 37: r_c for an agent within eta_c (m) of the centroid, else 0."""
    return r_c if centroid_distance <= eta_c else 0.0


@numba.njit(cache=True)
def goal_term(
    previous_way: float,
    way: float,
    goal_distance: float,
    eta_g: float,
    r_reached: float,
    k1: float,
    dt: float,
    v_max: float,
) -> float:  # pragma: no cover - compiled
    """Eqs 23 / 38: r_reached once the centroid is within eta_g of the goal (``goal_distance``, c_g,t+1), else
    k_1 + (w_t - w_t+1) / (dt v_max), w the way to the goal: c_g itself (the thesis's) or the way round the shapes
    (``goal_progress: geodesic``)."""
    if goal_distance <= eta_g:
        return r_reached
    return k1 + (previous_way - way) / (dt * v_max)


@numba.njit(cache=True)
def collision_term(agent_contact: bool, obstacle_near: bool, r_j: float, r_o: float) -> float:  # pragma: no cover
    """Eqs 24 / 39 (and 31 for the team): r_j for touching an agent, else r_o for being closer than d_safe to an obstacle."""
    if agent_contact:
        return r_j
    return r_o if obstacle_near else 0.0


@numba.njit(cache=True)
def nearest_gaps(
    positions: np.ndarray,
    agent_radius: float,
    obstacles: np.ndarray,
    walls: np.ndarray,
    width: float,
    height: float,
    flying: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Centre distance to the nearest other agent, and surface gap to the nearest circle, wall or border, of every agent.
    An agent that no longer flies is an obstacle to the others (a circle of radius R_a), not an agent.

    :param positions: ``(n, 2)`` agent centres (m)
    :param agent_radius: R_a (m)
    :param obstacles: ``(m, 3)`` circles (x, y, radius) in m
    :param walls: ``(w, 5)`` walls (x0, y0, x1, y1, thickness) in m
    :param width: world width (m)
    :param height: world height (m)
    :param flying: ``(n,)`` bool: the agents that fly
    :return: ``(n,)`` nearest agent centre distance (m) and ``(n,)`` nearest obstacle gap (m, negative when sunk in)
    """
    n_agents = positions.shape[0]
    nearest_agent = np.full(n_agents, np.inf)
    nearest_obstacle = shape_gaps(positions, obstacles, walls, width, height) - agent_radius
    for agent in range(n_agents):
        x, y = positions[agent, 0], positions[agent, 1]
        for other in range(n_agents):
            if other == agent:
                continue
            if flying[other]:
                nearest_agent[agent] = min(nearest_agent[agent], math.hypot(positions[other, 0] - x, positions[other, 1] - y))
            else:  # as shape_gaps measures a circle, then less the agent's radius
                gap = circle_gap(x, y, np.array((positions[other, 0], positions[other, 1], agent_radius))) - agent_radius
                nearest_obstacle[agent] = min(nearest_obstacle[agent], gap)
    return nearest_agent, nearest_obstacle


class RewardConstants(NamedTuple):
    """The constants of Tables 4.1 / 5.1 that the reward terms use (:func:`reward_constants`)."""

    m_ang_deg: float  #: m_ang (deg)
    d_ref: float  #: d^ref (m)
    m_dist: float  #: m_dist (m)
    eta_c: float  #: eta_c (m)
    r_c: float  #: r_c
    eta_g: float  #: eta_g (m)
    r_reached: float  #: r_reached
    k1: float  #: k_1
    dt: float  #: step length (s)
    v_max: float  #: v_max (m/s)
    r_j: float  #: r_j
    r_o: float  #: r_o
    d_safe: float  #: d_safe (m)
    r_late: float  #: r_late
    agent_radius: float  #: R_a (m)
    max_steps: int  #: T_s
    team_reward: bool  #: every agent receives the team averages (eqs 27-32)


def reward_constants(config: FormationConfig) -> RewardConstants:
    """The constants of ``config`` that :func:`reward_terms` needs, for the compiled kernel."""
    floats = {name: float(getattr(config, name)) for name in RewardConstants._fields[:-2]}
    return RewardConstants(**floats, max_steps=int(config.max_steps), team_reward=bool(config.team_reward))


@numba.njit(cache=True)
def _reward_terms(
    step: int,
    formation: FormationState,
    ways: tuple[float, float, float],
    velocities: tuple[np.ndarray, np.ndarray],
    neighbours: np.ndarray,
    gaps: tuple[np.ndarray, np.ndarray],
    constants: RewardConstants,
    terms: np.ndarray,
    flying: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Compiled core of :func:`reward_terms`: every term into ``terms``, ``(len(REWARD_TERMS), n)``.

    :param step: step count t + 1 after this step
    :param formation: the formation after the step (its angle and bearing errors, neighbour and centroid distances)
    :param ways: the way (m) to the goal before and after the step, and the goal distance (m) after it (:func:`goal_term`)
    :param velocities: ``(n, 2)`` velocities (m/s) before and after the step
    :param neighbours: ``(n, k)`` int64 neighbour indices
    :param gaps: ``(n,)`` centre distance (m) to the nearest other agent, and ``(n,)`` surface gap (m) to the nearest
        obstacle or wall
    :param constants: :func:`reward_constants`
    :param terms: where the terms go, row ``TERM_ROW[name]`` for term ``name``
    :param flying: ``(n,)`` bool: the agents that fly; the team's averages and collision term are theirs
    """
    previous_way, way, goal_distance = ways
    previous_velocities, now = velocities
    nearest_agent_distances, nearest_obstacle_gaps = gaps
    c = constants
    n_agents = now.shape[0]
    touching, near = False, False  # any agent touching another; any closer than d_safe to an obstacle
    for agent in range(n_agents):
        agent_contact = nearest_agent_distances[agent] <= 2.0 * c.agent_radius
        obstacle_near = nearest_obstacle_gaps[agent] < c.d_safe
        if flying[agent]:
            touching, near = touching or agent_contact, near or obstacle_near
        terms[_ANGLE, agent] = angle_term(formation.angle_errors_deg[agent], c.m_ang_deg)
        terms[_BEARING, agent] = bearing_term(formation.bearing_errors[agent])
        terms[_DIST, agent] = distance_term(formation.neighbour_distances[agent], c.d_ref, c.m_dist)
        terms[_CENTROID, agent] = centroid_term(formation.centroid_distances[agent], c.eta_c, c.r_c)
        terms[_MOVE, agent] = -angle_between(previous_velocities[agent], now[agent])
        alignment = 0.0
        for neighbour in neighbours[agent]:
            alignment += angle_between(now[agent], previous_velocities[neighbour])
        terms[_VELOCITY, agent] = -alignment / neighbours.shape[1]
        terms[_COLL, agent] = collision_term(agent_contact, obstacle_near, c.r_j, c.r_o)
    if c.team_reward:  # eqs 28-31: per-agent terms become team averages; one team collision term
        for row in (_ANGLE, _BEARING, _DIST, _CENTROID, _MOVE, _VELOCITY):
            terms[row, :] = flying_mean(terms[row], flying)
        terms[_COLL, :] = collision_term(touching, near, c.r_j, c.r_o)
    terms[_GOAL, :] = goal_term(previous_way, way, goal_distance, c.eta_g, c.r_reached, c.k1, c.dt, c.v_max)
    terms[_TIME, :] = time_term(step, c.max_steps, c.r_late)


@numba.njit(cache=True)
def flying_mean(values: np.ndarray, flying: np.ndarray) -> float:  # pragma: no cover - compiled
    """The mean of the flying agents' ``values``, summed in order (with every agent flying, numba's mean)."""
    total, count = 0.0, 0
    for agent in range(values.shape[0]):
        if flying[agent]:
            total, count = total + values[agent], count + 1
    return total / count


def reward_terms(
    config: FormationConfig,
    step: int,
    formation: FormationState,
    previous_goal_distance: float,
    goal_distance: float,
    previous_velocities: np.ndarray,
    velocities: np.ndarray,
    neighbours: np.ndarray,
    nearest_agent_distances: np.ndarray,
    nearest_obstacle_gaps: np.ndarray,
    constants: RewardConstants | None = None,
    ways: tuple[float, float] | None = None,
) -> np.ndarray:
    """Every reward term of one step, before coefficients.

    :param config: task configuration (constants of Tables 4.1 / 5.1, ``team_reward``)
    :param step: step count t + 1 after this step
    :param formation: formation measured after the step (:func:`~sb3_formation.env.geometry.measure_formation`)
    :param previous_goal_distance: centroid-goal distance (m) before the step
    :param goal_distance: centroid-goal distance (m) after the step
    :param previous_velocities: ``(n, 2)`` velocities (m/s) before the step
    :param velocities: ``(n, 2)`` velocities (m/s) after the step
    :param neighbours: ``(n, k)`` int64 neighbour indices
    :param nearest_agent_distances: ``(n,)`` centre distance (m) to the nearest other agent
    :param nearest_obstacle_gaps: ``(n,)`` surface gap (m) to the nearest obstacle or wall
    :param constants: ``reward_constants(config)``, if already made
    :param ways: the way (m) to the goal before and after the step whose decrease the goal term rewards
        (``goal_progress: geodesic``); ``None``: the centroid-goal distances (the thesis's)
    Arrays are float64 unless said otherwise.
    :return: ``(len(REWARD_TERMS), n)`` array; row ``TERM_ROW[name]`` holds term ``name``
    """
    previous_way, way = (previous_goal_distance, goal_distance) if ways is None else ways
    terms = np.empty((_N_TERMS, len(velocities)))
    _reward_terms(
        step,
        formation,
        (float(previous_way), float(way), float(goal_distance)),
        (previous_velocities, velocities),
        neighbours,
        (nearest_agent_distances, nearest_obstacle_gaps),
        reward_constants(config) if constants is None else constants,
        terms,
        np.ones(len(velocities), dtype=np.bool_),
    )
    return terms


def combine_rewards(terms: np.ndarray, coefficients: np.ndarray, clip: float) -> np.ndarray:
    """Eqs 26 / 32 / 42: sum_k K_k * term_k per agent, clipped to [-clip, clip]; for one team or a stack of teams.

    :param terms: ``(len(REWARD_TERMS), n)`` values before coefficients, or ``(teams, len(REWARD_TERMS), n)``
    :param coefficients: ``(len(REWARD_TERMS),)`` coefficients (0 for a term switched off), or one row per team
    :param clip: clip bound
    :return: ``(n,)`` rewards, or ``(teams, n)``
    """
    sums = (coefficients[..., None, :] @ terms)[..., 0, :]
    rewards: np.ndarray = np.minimum(np.maximum(sums, -clip), clip)
    return rewards
