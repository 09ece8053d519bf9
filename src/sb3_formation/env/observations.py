"""The per-agent observation of thesis Table 3.1: its fields, their order, honest bounds, and the one row builder.

Order (``docs/design.md`` "Sensors and observation"): lidar l, state z, errors e, flags f, then previous action /
reward / time step s; then what the dynamics add (a unicycle's heading,
:meth:`~sb3_formation.env.dynamics.DynamicsModel.observed_fields`); with ``FormationConfig.observe_reference_bearings``
(a departure, for teams of several sizes) the agent's reference bearings come last. Raw values in SI units and
degrees; normalisation belongs to the SB3 layer.

:func:`observation_row` writes one agent's row from its team's motion and formation, its lidar and what it remembers;
it is compiled, and both the engine's kernel (:func:`_fill_observations`, every agent of a team) and the on-board
observer (:class:`~sb3_formation.ros.observer.AgentObserver`, from Python) call it, so a row is defined once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numba
import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.env.geometry import FormationState
from sb3_formation.env.stacked import team_formation

if TYPE_CHECKING:
    from sb3_formation.env.stacked import Constants, Episodes, Formations

#: Relative slack on velocity bounds: a clamped speed may exceed v_max by a rounding error.
ROUNDING_SLACK = 1e-9


@dataclass(frozen=True)
class ObservationField:
    """One entry of Table 3.1.

    :param name: key in ``env.observation_layout``
    :param symbol: the thesis's symbol
    :param size: number of values
    :param low: lower bound of every value
    :param high: upper bound of every value
    :param unit: unit of the values
    :param binary: a 0/1 flag (left alone by normalisation)
    """

    name: str
    symbol: str
    size: int
    low: np.ndarray
    high: np.ndarray
    unit: str
    binary: bool = False


def observation_fields(config: FormationConfig) -> list[ObservationField]:
    """The fields of one agent's observation, in order, with bounds that hold for every reachable state."""
    rays = config.lidar_rays
    width, height, diagonal = config.world_width, config.world_height, config.world_diagonal
    speed = config.v_max * (1 + ROUNDING_SLACK)
    extent = np.array([width, height])
    model = dynamics_model(config)
    angle_low, angle_high = config.beta_ref_deg - 360.0, config.beta_ref_deg
    specs = [
        ("lidar_obstacles", "l (obstacles, walls)", rays, 0.0, 1.0, "fraction of range"),
        ("lidar_agents", "l (non-neighbour agents)", rays, 0.0, 1.0, "fraction of range"),
        ("velocity", "v^i", 2, -speed, speed, "m/s"),
        ("neighbour_offsets", "d_j^iv (preceding x, y; succeeding x, y)", 4, -np.tile(extent, 2), np.tile(extent, 2), "m"),
        ("neighbour_relative_velocities", "v_j^i = v^j - v^i", 4, -2 * speed, 2 * speed, "m/s"),
        ("goal_offset", "d_g^iv = p^g - p^i", 2, -extent, extent, "m"),
        ("centroid_goal_offset", "c_g^v = p^g - p^c", 2, -extent, extent, "m"),
        ("centroid_goal_offset_change", "c_g,t^v - c_g,t-1^v", 2, -extent, extent, "m"),
        ("neighbour_distances", "d_j^i", 2, 0.0, diagonal, "m"),
        ("centroid_distance", "d_c^i", 1, 0.0, diagonal, "m"),
        ("neighbour_distance_errors", "d_j^i - d^ref", 2, -config.d_ref, diagonal - config.d_ref, "m"),
        ("centroid_distance_error", "eta_c - d_c^i", 1, config.eta_c - diagonal, config.eta_c, "m"),
        ("angle_error", "beta^ref - beta^i", 1, angle_low, angle_high, "deg"),
        ("neighbour_angle_errors", "beta^ref - beta^j, j in N_2^i", 2, angle_low, angle_high, "deg"),
        ("flag_orientation", "f: beta^i in (0, 180)", 1, 0.0, 1.0, "0/1"),
        ("flag_range", "f: all neighbours within d^ref", 1, 0.0, 1.0, "0/1"),
        ("time_step", "t", 1, 0.0, float(config.max_steps), "steps"),
        ("previous_action", "a_t-1^i", 2, -1.0, 1.0, model.action_unit),
        ("previous_reward", "r_t-1^i", 1, -config.reward_clip, config.reward_clip, "reward"),
    ]
    specs.extend(model.observed_fields())  # what the dynamics add to Table 3.1 (a unicycle's heading)
    if config.observe_reference_bearings:  # a departure from Table 3.1 (FormationConfig.observe_reference_bearings)
        specs.append(("reference_bearings", "g_j^{i,ref} (preceding x, y; succeeding x, y)", 4, -1.0, 1.0, "unit"))
    return [
        ObservationField(
            name,
            symbol,
            size,
            np.broadcast_to(np.asarray(low, dtype=np.float64), (size,)),
            np.broadcast_to(np.asarray(high, dtype=np.float64), (size,)),
            unit,
            binary=name.startswith("flag_"),
        )
        for name, symbol, size, low, high, unit in specs
    ]


def observation_layout(fields: list[ObservationField]) -> dict[str, slice]:
    """Field name -> slice of the observation vector."""
    layout, start = {}, 0
    for field in fields:
        layout[field.name] = slice(start, start + field.size)
        start += field.size
    return layout


class RowTask(NamedTuple):
    """What a team's rows share: its agents' neighbours and reference bearings (agent 0 first, indices within the team)
    and the task's constants."""

    neighbours: np.ndarray  #: ``(n, 2)`` int64: each agent's preceding and succeeding neighbour
    reference_bearings: np.ndarray  #: ``(n, 2, 2)`` reference bearings g_j^{i,ref}
    d_ref: float  #: reference neighbour distance d^ref (m)
    eta_c: float  #: centroid distance eta_c (m)
    observe_reference: bool  #: a row ends with the agent's reference bearings


class AgentInputs(NamedTuple):
    """What one agent's row takes beyond its team's motion and formation and its lidar."""

    goal: np.ndarray  #: ``(2,)`` the goal (m)
    previous_offset: np.ndarray  #: ``(2,)`` the team's c_g^v = p^g - p^c one step earlier (m)
    step: float  #: steps since the reset
    previous_action: np.ndarray  #: ``(2,)`` the agent's action of the last step
    previous_reward: float  #: the agent's reward of the last step
    observed: np.ndarray  #: ``(e,)`` what its dynamics add (:meth:`~sb3_formation.env.dynamics.DynamicsModel.observed_values`)


@numba.njit(cache=True)
def observation_row(
    out: np.ndarray,
    agent: int,
    positions: np.ndarray,
    velocities: np.ndarray,
    formation: FormationState,
    lidar: np.ndarray,
    inputs: AgentInputs,
    task: RowTask,
) -> None:  # pragma: no cover - compiled
    """Write one agent's observation into ``out`` (its row, ``(dim,)``), in the order of :func:`observation_fields`.

    :param agent: the agent's index in its team
    :param positions: ``(n, 2)`` its team's positions (m)
    :param velocities: ``(n, 2)`` its team's velocities (m/s)
    :param formation: its team's formation (angle errors and flags included)
    :param lidar: ``(2, rays)`` its obstacle and agent channels, fractions of the range
    :param inputs: its goal, memory and dynamics' values
    :param task: its team's neighbours and reference bearings, and the task's constants
    """
    n_rays, goal, centroid, previous_offset = lidar.shape[1], inputs.goal, formation.centroid, inputs.previous_offset
    offsets, distances = formation.neighbour_offsets, formation.neighbour_distances
    centroid_distances, angle_errors = formation.centroid_distances, formation.angle_errors_deg
    out[:n_rays] = lidar[0]
    out[n_rays : 2 * n_rays] = lidar[1]
    preceding, succeeding = task.neighbours[agent, 0], task.neighbours[agent, 1]
    motion_and_distances = (  # velocity ... centroid_distance of observation_fields
        velocities[agent, 0],
        velocities[agent, 1],
        offsets[agent, 0, 0],
        offsets[agent, 0, 1],
        offsets[agent, 1, 0],
        offsets[agent, 1, 1],
        velocities[preceding, 0] - velocities[agent, 0],
        velocities[preceding, 1] - velocities[agent, 1],
        velocities[succeeding, 0] - velocities[agent, 0],
        velocities[succeeding, 1] - velocities[agent, 1],
        goal[0] - positions[agent, 0],
        goal[1] - positions[agent, 1],
        goal[0] - centroid[0],
        goal[1] - centroid[1],
        goal[0] - centroid[0] - previous_offset[0],
        goal[1] - centroid[1] - previous_offset[1],
        distances[agent, 0],
        distances[agent, 1],
        centroid_distances[agent],
    )
    errors_flags_and_previous = (  # neighbour_distance_errors ... previous_reward
        distances[agent, 0] - task.d_ref,
        distances[agent, 1] - task.d_ref,
        task.eta_c - centroid_distances[agent],
        angle_errors[agent],
        angle_errors[preceding],
        angle_errors[succeeding],
        1.0 if formation.orientation_flags[agent] else 0.0,
        1.0 if formation.range_flag else 0.0,
        inputs.step,
        inputs.previous_action[0],
        inputs.previous_action[1],
        inputs.previous_reward,
    )
    column = _write(out, 2 * n_rays, motion_and_distances)
    column = _write(out, column, errors_flags_and_previous)
    for value in inputs.observed:  # the dynamics' fields
        out[column] = value
        column += 1
    if task.observe_reference:  # the last four columns
        for k in range(4):
            out[column + k] = task.reference_bearings[agent, k // 2, k % 2]


@numba.njit(cache=True)
def _fill_observations(
    team: int,
    constants: Constants,
    formations: Formations,
    motion: tuple[np.ndarray, np.ndarray],
    out: np.ndarray,
    episodes: Episodes,
    observed: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """A team's agents' observations (:func:`observation_row`), written into their rows of ``out``.

    :param formations: every team's formation as its agents measure it
    :param motion: every agent's position (m) and velocity (m/s) as its agents know them, ``(agents, 2)`` each
    :param out: ``(agents, dim)`` every agent's observation
    :param observed: ``(agents, e)`` what every agent's dynamics add to its row
    """
    start, end = constants.starts[team], constants.starts[team + 1]
    formation = team_formation(team, constants.starts, formations)
    task = RowTask(
        constants.neighbours[start:end],
        constants.reference_bearings[start:end],
        constants.d_ref,
        constants.eta_c,
        constants.observe_reference,
    )
    positions, velocities = motion[0][start:end], motion[1][start:end]
    goal, previous_offset, step = episodes.goals[team], episodes.previous_offsets[team], float(episodes.step_counts[team])
    for agent in range(end - start):
        row = start + agent
        inputs = AgentInputs(
            goal, previous_offset, step, episodes.previous_actions[row], episodes.previous_rewards[row], observed[row]
        )
        observation_row(out[row], agent, positions, velocities, formation, episodes.lidar[:, row], inputs, task)


@numba.njit(cache=True)
def _write(row: np.ndarray, column: int, values: tuple[float, ...]) -> int:  # pragma: no cover - compiled
    """Write ``values`` into ``row`` from ``column`` on; return the column after them."""
    for value in values:
        row[column] = value
        column += 1
    return column
