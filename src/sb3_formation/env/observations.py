"""The per-agent observation of thesis Table 3.1: its fields, their order, honest bounds, and the compiled filler.

Order (``docs/design.md`` "Sensors and observation"): lidar l, state z, errors e, flags f, then previous action /
reward / time step s; with ``FormationConfig.observe_reference_bearings`` (a departure, for teams of several sizes)
the agent's reference bearings come last. Raw values in SI units and degrees; normalisation belongs to the SB3 layer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.dynamics import dynamics_model

if TYPE_CHECKING:
    from sb3_formation.env.stacked import Constants, Episodes, Formations, StepArrays

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


@numba.njit(cache=True)
def _fill_observations(
    team: int, constants: Constants, formations: Formations, latest: StepArrays, episodes: Episodes
) -> None:  # pragma: no cover - compiled
    """A team's agents' observations, written into their rows of ``latest.observations`` in the order of
    :func:`observation_fields` (a unicycle's heading, when observed, is written by its dynamics)."""
    start, end = constants.starts[team], constants.starts[team + 1]
    out, lidar, neighbours = latest.observations, episodes.lidar, constants.neighbours
    velocities, positions = latest.velocities, latest.positions
    offsets, distances = formations.neighbour_offsets, formations.neighbour_distances
    centroid_distances, angle_errors = formations.centroid_distances, formations.angle_errors_deg
    goal, centroid, previous_offset = episodes.goals[team], formations.centroids[team], episodes.previous_offsets[team]
    range_flag, step = formations.range_flags[team], episodes.step_counts[team]
    d_ref, eta_c, n_rays, dim = constants.d_ref, constants.eta_c, lidar.shape[2], out.shape[1]
    for row in range(start, end):
        observation = out[row]
        observation[:n_rays] = lidar[0, row]
        observation[n_rays : 2 * n_rays] = lidar[1, row]
        preceding, succeeding = start + neighbours[row, 0], start + neighbours[row, 1]
        motion_and_distances = (  # velocity ... centroid_distance of observation_fields
            velocities[row, 0],
            velocities[row, 1],
            offsets[row, 0, 0],
            offsets[row, 0, 1],
            offsets[row, 1, 0],
            offsets[row, 1, 1],
            velocities[preceding, 0] - velocities[row, 0],
            velocities[preceding, 1] - velocities[row, 1],
            velocities[succeeding, 0] - velocities[row, 0],
            velocities[succeeding, 1] - velocities[row, 1],
            goal[0] - positions[row, 0],
            goal[1] - positions[row, 1],
            goal[0] - centroid[0],
            goal[1] - centroid[1],
            goal[0] - centroid[0] - previous_offset[0],
            goal[1] - centroid[1] - previous_offset[1],
            distances[row, 0],
            distances[row, 1],
            centroid_distances[row],
        )
        errors_flags_and_previous = (  # neighbour_distance_errors ... previous_reward
            distances[row, 0] - d_ref,
            distances[row, 1] - d_ref,
            eta_c - centroid_distances[row],
            angle_errors[row],
            angle_errors[preceding],
            angle_errors[succeeding],
            1.0 if formations.orientation_flags[row] else 0.0,
            1.0 if range_flag else 0.0,
            float(step),
            episodes.previous_actions[row, 0],
            episodes.previous_actions[row, 1],
            episodes.previous_rewards[row],
        )
        column = _write(observation, 2 * n_rays, motion_and_distances)
        _write(observation, column, errors_flags_and_previous)
        if constants.observe_reference:  # the last four columns
            for k in range(4):
                observation[dim - 4 + k] = constants.reference_bearings[row, k // 2, k % 2]


@numba.njit(cache=True)
def _write(row: np.ndarray, column: int, values: tuple[float, ...]) -> int:  # pragma: no cover - compiled
    """Write ``values`` into ``row`` from ``column`` on; return the column after them."""
    for value in values:
        row[column] = value
        column += 1
    return column
