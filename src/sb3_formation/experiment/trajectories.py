"""Step-by-step records of evaluation episodes: recording them while they are played, stacking them into
:class:`Trajectories`, and the ``trajectories.npz`` file."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sb3_formation.env.blocks import BlockStep
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import ContactColumn, InfoColumn
from sb3_formation.env.geometry import ring_neighbours
from sb3_formation.env.state import TeamState
from sb3_formation.utils.files import atomic_write

#: Per-step, per-agent arrays of :class:`Trajectories` -> where a step's arrays hold them: a column of the info values
#: or of the contacts
STEP_RECORDS: dict[str, tuple[str, int]] = {
    "angle_error_deg": ("info_values", InfoColumn.ANGLE_ERROR_DEG),
    "bearing_error": ("info_values", InfoColumn.BEARING_ERROR),
    "neighbour_distance_error": ("info_values", InfoColumn.NEIGHBOUR_DISTANCE_ERROR),
    "collisions_obstacle": ("contacts", ContactColumn.OBSTACLES),
    "collisions_agent": ("contacts", ContactColumn.AGENTS),
}


@dataclass
class Trajectories:
    """Step-by-step records of evaluation episodes, padded with NaN after each episode's end.

    Row 0 of the per-step arrays is the state after ``reset``; row t (1 <= t <= ``lengths[k]``) is the state after
    step t. Errors, collisions and actions have no value in row 0 (NaN). Error columns are those of the agents' step
    infos: ``angle_error_deg`` = abs(beta_ref - beta^i) (deg), ``bearing_error`` = half the sum of norm(g_ref - g) over
    the two neighbours, ``neighbour_distance_error`` = half the sum of max(d_j^i - d_ref, 0) (m), collisions = contacts
    of the agent that step.

    :param config: task configuration of the episodes
    :param episodes: ``(K,)`` evaluation episode indices
    :param seeds: ``(K,)`` reset seeds
    :param lengths: ``(K,)`` steps played
    :param success: ``(K,)`` whether the centroid reached the goal
    :param goals: ``(K, 2)`` goal positions (m)
    :param obstacles: ``(K, M, 3)`` obstacle x, y, radius (m), NaN rows when an episode has fewer
    :param positions: ``(K, T + 1, n, 2)`` agent positions (m)
    :param velocities: ``(K, T + 1, n, 2)`` agent velocities (m/s)
    :param actions: ``(K, T + 1, n, 2)`` actions applied in the step that led to the row (clipped to [-1, 1])
    :param angle_error_deg: ``(K, T + 1, n)``
    :param bearing_error: ``(K, T + 1, n)``
    :param neighbour_distance_error: ``(K, T + 1, n)``
    :param collisions_obstacle: ``(K, T + 1, n)``
    :param collisions_agent: ``(K, T + 1, n)`` (each touching pair counted by both agents)
    :param goal_distance: ``(K, T + 1)`` centroid-goal distance (m)
    :param walls: ``(K, W, 5)`` walls x0, y0, x1, y1, thickness (m), NaN rows when an episode has fewer (files written
        before walls existed have none)
    """

    config: FormationConfig
    episodes: np.ndarray
    seeds: np.ndarray
    lengths: np.ndarray
    success: np.ndarray
    goals: np.ndarray
    obstacles: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    actions: np.ndarray
    angle_error_deg: np.ndarray
    bearing_error: np.ndarray
    neighbour_distance_error: np.ndarray
    collisions_obstacle: np.ndarray
    collisions_agent: np.ndarray
    goal_distance: np.ndarray
    walls: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 5)))

    def __post_init__(self) -> None:
        if len(self.walls) != len(self.episodes):  # a file written before walls existed: none
            self.walls = np.zeros((len(self.episodes), 0, 5))

    def __len__(self) -> int:
        return len(self.episodes)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write every array (and the configuration as JSON) to an ``.npz`` file, atomically."""
        path = Path(path)
        arrays = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "config"}
        arrays["config_json"] = np.array(json.dumps(self.config.to_dict()))
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **arrays)
        atomic_write(path, buffer.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Trajectories:
        """Read a file written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no trajectories at {path}: run `sb3-formation evaluate` first")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
            config = FormationConfig.from_dict(json.loads(str(arrays.pop("config_json"))))
            return cls(config=config, **arrays)
        except (KeyError, TypeError, ValueError, OSError, zipfile.BadZipFile) as error:
            raise ValueError(f"{path} is not a trajectories file written by sb3-formation: {error}") from error

    def steps(self, index: int) -> dict[str, np.ndarray]:
        """The per-step arrays of the ``index``-th recorded episode without padding (``lengths[index] + 1`` rows)."""
        rows = int(self.lengths[index]) + 1
        names = (*STEP_RECORDS, "positions", "velocities", "actions", "goal_distance")
        return {name: getattr(self, name)[index, :rows] for name in names}

    def team_state(self, index: int, step: int) -> TeamState:
        """The recorded team's state after ``step`` of the ``index``-th recorded episode (no lidar readings), e.g. to
        draw it with :func:`~sb3_formation.env.rendering.render_frame` without replaying the policy."""
        if not 0 <= step <= int(self.lengths[index]):
            raise IndexError(f"step {step} is outside episode {int(self.episodes[index])}'s 0 to {int(self.lengths[index])}")
        obstacles, walls = self.obstacles[index], self.walls[index]
        zeros = np.zeros(self.config.n_agents, dtype=np.int64)
        counts = {
            name: np.nan_to_num(getattr(self, name)[index, step]).astype(np.int64)
            for name in ("collisions_agent", "collisions_obstacle")
        }
        return TeamState(
            step=step,
            positions=self.positions[index, step],
            velocities=self.velocities[index, step],
            goal=self.goals[index],
            obstacles=obstacles[~np.isnan(obstacles).any(axis=1)],
            neighbours=ring_neighbours(self.config.n_agents),
            contacts_agent=counts["collisions_agent"] if step else zeros,
            contacts_obstacle=counts["collisions_obstacle"] if step else zeros,
            angle_errors_deg=self.angle_error_deg[index, step],
            bearing_errors=self.bearing_error[index, step],
            neighbour_distance_errors=self.neighbour_distance_error[index, step],
            centroid=self.positions[index, step].mean(axis=0),
            goal_distance=float(self.goal_distance[index, step]),
            walls=walls[~np.isnan(walls).any(axis=1)],
        )


class EpisodeRecorder:
    """Collects one episode's per-step records for :class:`Trajectories`: the state after the reset, then each step's
    arrays."""

    def __init__(self, state: TeamState) -> None:
        n_agents = state.n_agents
        nan = np.full(n_agents, np.nan)
        self.goal, self.obstacles, self.walls = state.goal, state.obstacles, state.walls
        self.rows: dict[str, list[np.ndarray]] = {name: [nan] for name in STEP_RECORDS}
        self.rows["positions"] = [state.positions]
        self.rows["velocities"] = [state.velocities]
        self.rows["actions"] = [np.full((n_agents, 2), np.nan)]
        self.rows["goal_distance"] = [np.array(state.goal_distance)]

    def add(self, step: BlockStep, slots: slice, actions: np.ndarray) -> None:
        """Add a step: the team's ``slots`` of the step's arrays, and the actions the policy gave."""
        for name, (array, column) in STEP_RECORDS.items():
            self.rows[name].append(getattr(step, array)[slots, column].astype(np.float64))
        self.rows["positions"].append(step.positions[slots].copy())
        self.rows["velocities"].append(step.velocities[slots].copy())
        self.rows["actions"].append(np.clip(actions[slots], -1.0, 1.0).astype(np.float64))
        self.rows["goal_distance"].append(np.array(step.info_values[slots.start, InfoColumn.GOAL_DISTANCE]))


def stack_recordings(
    config: FormationConfig, seed: int, recorded: list[tuple[int, EpisodeRecorder, bool]]
) -> Trajectories | None:
    """Pad the recorded episodes (of an evaluation with ``seed``) to one length and stack them, in episode order."""
    if not recorded:
        return None
    recorded = sorted(recorded, key=lambda item: item[0])
    lengths = np.array([len(recorder.rows["positions"]) - 1 for _, recorder, _ in recorded], dtype=np.int64)
    rows = int(lengths.max()) + 1
    arrays: dict[str, np.ndarray] = {}
    for name in recorded[0][1].rows:
        padded = []
        for _, recorder, _ in recorded:
            values = np.stack(recorder.rows[name]).astype(np.float64)
            pad = np.full((rows - len(values), *values.shape[1:]), np.nan)
            padded.append(np.concatenate([values, pad]))
        arrays[name] = np.stack(padded)
    shapes = {}
    for name, columns in (("obstacles", 3), ("walls", 5)):
        most = max(len(getattr(recorder, name)) for _, recorder, _ in recorded)
        shapes[name] = np.full((len(recorded), most, columns), np.nan)
        for index, (_, recorder, _) in enumerate(recorded):
            shapes[name][index, : len(getattr(recorder, name))] = getattr(recorder, name)
    episodes = np.array([episode for episode, _, _ in recorded], dtype=np.int64)
    return Trajectories(
        config=config,
        episodes=episodes,
        seeds=episodes + seed,
        lengths=lengths,
        success=np.array([success for _, _, success in recorded], dtype=bool),
        goals=np.stack([recorder.goal for _, recorder, _ in recorded]).astype(np.float64),
        **shapes,
        **arrays,
    )
