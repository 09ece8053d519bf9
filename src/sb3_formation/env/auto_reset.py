"""Automatic resets and episode records: what an episode loop adds to an engine, for the teams one process steps.

An :class:`EngineBlock` is a :class:`~sb3_formation.env.engine.FormationEngine` of some teams with what an episode
loop adds to it: the slots' observations (:func:`~sb3_formation.env.slots.slot_observations`), terminal
observations, the record of every episode that ends (:class:`TeamEpisode`), and, with ``auto_reset``, the reset of a
team in the step that ends its episode, as a ``VecEnv`` does. A step gives its arrays as a :class:`BlockStep`, whose
arrays :func:`step_layout` describes for shared memory; :class:`~sb3_formation.env.blocks.EngineBlocks` spreads blocks
over processes.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import INFO_VALUES, FormationEngine
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.slots import slot_observations
from sb3_formation.env.state import TeamState
from sb3_formation.utils.processes import SharedArrays


class TeamEpisode(NamedTuple):
    """A team's episode that ended in a step."""

    team: int  #: within the block (:meth:`~sb3_formation.env.blocks.EngineBlocks.step`: of all blocks)
    first_slot: int  #: within the block (:meth:`~sb3_formation.env.blocks.EngineBlocks.step`: of all blocks)
    terminal_observations: np.ndarray
    timed_out: bool
    success: bool
    episode: dict[str, float]  #: SB3's record: team return, length, time
    summary: dict[str, Any]  #: ``formation_episode``
    comm_exceeded_steps: int  #: steps with a neighbour beyond d_comm


class BlockStep(NamedTuple):
    """One step of a block of teams, as arrays (:meth:`EngineBlock.step`), then the block's ended episodes."""

    observations: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    info_values: np.ndarray
    contacts: np.ndarray
    success: np.ndarray  #: per slot
    positions: np.ndarray
    velocities: np.ndarray
    flying: np.ndarray  #: per slot: the agent's motors run (after the step's resets; see ``FormationEngine.fail``)
    episodes: list[TeamEpisode]


#: the :class:`BlockStep` fields that are arrays with a row per slot
ARRAY_FIELDS = BlockStep._fields[:-1]


def step_layout(slots: int, observation_dim: int) -> dict[str, tuple[tuple[int, ...], Any]]:
    """Shapes and dtypes of a block's actions and :class:`BlockStep` arrays, for ``slots`` slots."""
    return {
        "actions": ((slots, 2), np.float64),
        "observations": ((slots, observation_dim), np.float32),
        "rewards": ((slots,), np.float64),
        "dones": ((slots,), bool),
        "info_values": ((slots, INFO_VALUES), np.float64),
        "contacts": ((slots, 3), np.int64),
        "success": ((slots,), bool),
        "positions": ((slots, 2), np.float64),
        "velocities": ((slots, 2), np.float64),
        "flying": ((slots,), bool),
    }


class EngineBlock:
    """The teams one process steps: an engine of them, with slots, episode records and (optionally) automatic resets.

    :param configs: task configuration of each team of this block
    :param team_observations: each slot also sees its whole team's observations (for a team critic)
    :param auto_reset: reset a team in the step that ends its episode (a ``VecEnv``'s convention); without it, a team
        that ended waits for :meth:`reset` and is not stepped
    :param render_mode: render mode of the teams' envs
    :param shared: the block's ``actions`` and :data:`ARRAY_FIELDS` arrays in shared memory, for
        :meth:`step_shared` (in a worker process)
    """

    def __init__(
        self,
        configs: Sequence[FormationConfig],
        team_observations: bool = False,
        auto_reset: bool = True,
        render_mode: str | None = None,
        shared: SharedArrays | None = None,
    ) -> None:
        self.engine = engine = FormationEngine(configs)
        if auto_reset and engine.unit_size > 1:
            raise ValueError(
                f"the {engine.config.scenes!r} scenes fly formations together and are played, not trained on: "
                "evaluate or benchmark a policy on them"
            )
        #: one PettingZoo view per team, for attribute and method calls
        self.envs = [FormationEnv(engine=engine, team=team, render_mode=render_mode) for team in range(engine.n_teams)]
        self.team_observations = team_observations
        self.auto_reset = auto_reset
        self.shared = shared
        self.start_time = time.time()

    def _slot_observations(self, own: np.ndarray, n_agents: int) -> np.ndarray:
        return slot_observations(own, n_agents, self.team_observations)

    def reset(
        self, teams: Sequence[int], seeds: Sequence[int | None], options: Sequence[dict[str, Any] | None]
    ) -> list[np.ndarray]:
        """Reset ``teams[j]`` with ``seeds[j]`` and ``options[j]`` (``{"scenario": ...}`` or empty). In a crossing
        (``FormationEngine.unit_size`` > 1) a unit's first team resets the unit; its other teams, listed after it,
        give their observations of that reset (their seeds and options unused).

        :return: each team's slots' observations, ``(n, obs_dim)``
        """
        engine, observations = self.engine, []
        for team, seed, team_options in zip(teams, seeds, options):
            if team % engine.unit_size == 0:
                own = engine.reset(team, seed, (team_options or {}).get("scenario"))
            elif team - team % engine.unit_size in teams[: teams.index(team)]:
                own = engine.latest.observations[engine.team_rows(team)].copy()
            else:
                raise ValueError(f"team {team} flies in the crossing of team {team - team % engine.unit_size}: reset both")
            observations.append(self._slot_observations(own, int(engine.sizes[team])))
        return observations

    def step(self, actions: np.ndarray) -> BlockStep:
        """Step every team in an episode with its agents' rows of ``actions``.

        :param actions: ``(slots, 2)`` finite actions (checked by the caller), each team's agents one after the other
        :return: the block's arrays (the caller builds info dicts from them: pickling dicts between processes would
            cost more than the step), and the episodes that ended
        """
        engine = self.engine
        step = engine.step(np.minimum(np.maximum(actions, -1.0), 1.0))
        observations = self._slot_observations(step.observations, int(engine.sizes[0]))  # team critics: one size
        ended = step.terminated | step.truncated
        episodes = []
        success: bool | np.ndarray  # a team's in the loop, then the slots'
        for team in np.flatnonzero(ended).tolist():
            rows = engine.team_rows(team)
            success = bool(step.terminated[team])
            summary = engine.episode_summary(team)
            record = {"r": summary["return"], "l": summary["length"], "t": round(time.time() - self.start_time, 6)}
            terminal = observations[rows].copy()  # with auto_reset, the rows get the reset's observations
            timed_out = bool(step.truncated[team]) and not success
            comm = int(engine.episodes.comm_exceeded[team])
            episodes.append(TeamEpisode(team, rows.start, terminal, timed_out, success, record, summary, comm))
            if self.auto_reset:
                observations[rows] = self._slot_observations(engine.reset(team), rows.stop - rows.start)
        dones, success = np.repeat(ended, engine.sizes), np.repeat(step.terminated, engine.sizes)
        arrays = (step.rewards, dones, step.info_values, step.contacts, success, step.positions, step.velocities)
        return BlockStep(observations, *arrays, engine.constants.flying.copy(), episodes)

    def step_shared(self) -> list[TeamEpisode]:
        """:meth:`step` with the actions read from ``shared`` and the arrays written to it: only the ended episodes
        (few, and rarely any) go through the worker's pipe."""
        assert self.shared is not None  # a worker's block, made with its shared arrays
        step = self.step(self.shared["actions"])
        for field in ARRAY_FIELDS:
            self.shared[field][...] = getattr(step, field)
        return step.episodes

    def get_attr(self, name: str, teams: Iterable[int]) -> list[Any]:
        """Attribute ``name`` of each of ``teams``' envs (indices within this block)."""
        return [getattr(self.envs[team], name) for team in teams]

    def set_attr(self, name: str, teams: Iterable[int], value: Any) -> None:
        """Set attribute ``name`` of each of ``teams``' envs."""
        for team in teams:
            setattr(self.envs[team], name, value)

    def env_method(self, name: str, teams: Iterable[int], args: tuple[Any, ...], kwargs: dict[str, Any]) -> list[Any]:
        """Call method ``name`` of each of ``teams``' envs."""
        return [getattr(self.envs[team], name)(*args, **kwargs) for team in teams]

    def team_states(self, teams: Iterable[int]) -> list[TeamState]:
        """Snapshots of ``teams`` now."""
        return [self.engine.team_state(team) for team in teams]

    def get_images(self) -> list[np.ndarray | None]:
        """One ``rgb_array`` frame per team."""
        return [env.render() for env in self.envs]

    def close(self) -> None:
        """Close every team's env (and this process's view of the shared arrays)."""
        for env in self.envs:
            env.close()
        if self.shared is not None:
            self.shared.close()
