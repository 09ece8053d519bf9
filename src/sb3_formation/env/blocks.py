"""Blocks of teams over processes: what the SB3 ``VecEnv`` and evaluation both step.

:class:`EngineBlocks` spreads teams over processes: this process steps the first block
(:class:`~sb3_formation.env.auto_reset.EngineBlock`), worker processes the others at the same time; actions and step
arrays go through shared memory, and only the ended episodes through a worker's pipe. Each team is independent, so the
same seeds give the same numbers for any number of processes.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any, cast

import numpy as np

from sb3_formation.env.auto_reset import ARRAY_FIELDS, BlockStep, EngineBlock, step_layout
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.scenes import scenes_named
from sb3_formation.utils.processes import SharedArrays, WorkerProcess, gather, wait_started, worker_context

#: what a step of the pool gives (:class:`~sb3_formation.env.auto_reset.BlockStep`) is importable from here too
__all__ = ["WORKER_SPIN", "BlockStep", "EngineBlocks"]

#: seconds a worker process polls for the next step before it sleeps (waking it would cost more than a step), and the
#: parent for a worker's reply; the steps of a rollout follow each other well within it, training phases do not
WORKER_SPIN = 0.02


class EngineBlocks:
    """Teams spread over processes, stepped at once: this process steps the first block of teams, ``n_workers - 1``
    worker processes one block each of the others.

    Teams are numbered over all blocks (block b holds the contiguous teams ``team_blocks[b]``), and so are slots.

    :param configs: task configuration of each team (they may differ in ``n_agents`` only)
    :param n_workers: processes stepping the teams, this one included
    :param team_observations: see :class:`EngineBlock`
    :param auto_reset: see :class:`EngineBlock`
    :param render_mode: see :class:`EngineBlock`
    :param start_method: multiprocessing start method for the workers (default: ``forkserver`` where available)
    """

    def __init__(
        self,
        configs: Sequence[FormationConfig],
        n_workers: int = 1,
        team_observations: bool = False,
        auto_reset: bool = True,
        render_mode: str | None = None,
        start_method: str | None = None,
    ) -> None:
        n_teams = len(configs)
        unit = scenes_named(configs[0].scenes).formations if configs else 1  # a crossing's formations share a block
        unit = unit if n_teams % unit == 0 else 1  # (other numbers of teams: the engine refuses them)
        if not (isinstance(n_workers, int) and 1 <= n_workers <= n_teams // unit):
            per = f" / {unit} formations per crossing" if unit > 1 else ""
            raise ValueError(f"n_workers must be an integer in [1, the number of teams {n_teams}{per}], got {n_workers!r}")
        sizes = [config.n_agents for config in configs]
        #: team j: slots ``team_starts[j]:team_starts[j + 1]``
        self.team_starts = np.concatenate([[0], np.cumsum(sizes)])
        #: the teams of each block (whole crossings)
        units = np.array_split(np.arange(n_teams // unit), n_workers)
        self.team_blocks = [list(range(block[0] * unit, (block[-1] + 1) * unit)) for block in units]
        local = EngineBlock([configs[team] for team in self.team_blocks[0]], team_observations, auto_reset, render_mode)
        dim = local.engine.observation_dim * (1 + sizes[0] if team_observations else 1)
        #: the first block's teams, stepped in this process; the others' in worker processes
        self.blocks: list[EngineBlock | WorkerProcess] = [local]
        #: per worker block: its actions and step arrays in shared memory
        self.shared: dict[int, SharedArrays] = {}
        try:
            if n_workers > 1:
                context = worker_context(start_method)
            for block, teams in enumerate(self.team_blocks[1:], start=1):
                self.shared[block] = shared = SharedArrays(step_layout(sum(sizes[team] for team in teams), dim))
                arguments = ([configs[team] for team in teams], team_observations, auto_reset, render_mode, shared)
                self.blocks.append(WorkerProcess(EngineBlock, arguments, "engine worker", context, WORKER_SPIN))
            wait_started(cast("list[WorkerProcess]", self.blocks[1:]))  # every block after the first
            for shared in self.shared.values():  # every process has mapped its block: no name to leave behind
                shared.unlink()
        except BaseException:
            self.close()
            raise

    @property
    def n_slots(self) -> int:
        return int(self.team_starts[-1])

    def checked_actions(self, actions: Any, teams: Sequence[int] | None = None) -> np.ndarray:
        """The slots' actions as an ``(slots, 2)`` float64 array, checked before any team steps.

        :param actions: ``(slots, 2)`` real numbers, one row per slot (or the same flattened, ``(slots * 2,)``)
        :param teams: the teams whose actions must be finite (default: every team)
        :raises ValueError: another shape, a value that is not a real number, or one that is not finite (naming its
            team and agent)
        """
        slots = self.n_slots
        array = np.asarray(actions) if isinstance(actions, (np.ndarray, list, tuple)) else None
        if array is None or array.dtype.kind not in "iuf":
            kind = type(actions).__name__ if array is None else f"dtype {array.dtype}"
            raise ValueError(f"actions must be an array of real numbers of shape ({slots}, 2), got {kind}")
        if array.shape == (slots * 2,):
            array = array.reshape(slots, 2)
        if array.shape != (slots, 2):
            raise ValueError(f"actions must have shape ({slots}, 2), one row per slot, got {array.shape}")
        array = array.astype(np.float64)
        finite = np.isfinite(array).all(axis=1)
        if teams is not None:
            finite |= ~np.repeat(np.isin(np.arange(len(self.team_starts) - 1), teams), np.diff(self.team_starts))
        bad = np.flatnonzero(~finite)
        if bad.size:
            slot = int(bad[0])
            team = int(np.searchsorted(self.team_starts, slot, side="right") - 1)
            agent = slot - int(self.team_starts[team])
            raise ValueError(f"team {team}: action of agent_{agent} is not finite: {array[slot].tolist()}")
        return array

    @property
    def local(self) -> EngineBlock:
        """The block this process steps."""
        return cast(EngineBlock, self.blocks[0])

    def _per_block(self, teams: Iterable[int]) -> list[tuple[int, list[int]]]:
        """Group teams by block: (block, indices within the block), blocks in order of first appearance."""
        grouped: dict[int, list[int]] = {}
        for team in teams:
            for block, block_teams in enumerate(self.team_blocks):
                if team in block_teams:
                    grouped.setdefault(block, []).append(team - block_teams[0])
        return list(grouped.items())

    def run(self, command: str, arguments: dict[int, tuple[Any, ...]], worker_command: str | None = None) -> dict[int, Any]:
        """Call ``command`` on the blocks in ``arguments`` (block -> arguments), the workers' while this process runs
        its own block's.

        :param worker_command: the workers' command instead of ``command``
        """
        workers = [block for block in arguments if block > 0]
        for block in workers:
            cast(WorkerProcess, self.blocks[block]).send(worker_command or command, *arguments[block])  # block > 0
        results = {}
        try:
            if 0 in arguments:
                results[0] = getattr(self.blocks[0], command)(*arguments[0])
        finally:  # read the workers' replies even after an error here, so none is left in a pipe
            results.update(
                zip(workers, gather([cast(WorkerProcess, self.blocks[block]) for block in workers], spin=WORKER_SPIN))
            )
        return results

    def call_teams(self, command: str, teams: Iterable[int], *data: Any) -> dict[int, Any]:
        """Run ``command(data[0], block_teams, *data[1:])`` on the blocks holding ``teams``; return team -> result
        (``None`` for a command without results).

        With no ``data``, ``command(block_teams)``.
        """
        grouped = self._per_block(teams)
        results = self.run(command, {block: (*data[:1], local, *data[1:]) for block, local in grouped})
        values: dict[int, Any] = {}
        for block, local in grouped:
            block_values = results[block] if results[block] is not None else [None] * len(local)
            values.update(zip((self.team_blocks[block][0] + team for team in local), block_values))
        return values

    def reset(
        self, teams: Sequence[int], seeds: Sequence[int | None], options: Sequence[dict[str, Any] | None]
    ) -> dict[int, np.ndarray]:
        """Reset ``teams[j]`` with ``seeds[j]`` and ``options[j]``; return each team's slots' observations."""
        by_team = {team: (seed, team_options) for team, seed, team_options in zip(teams, seeds, options)}
        arguments = {}
        for block, local in self._per_block(teams):
            first = self.team_blocks[block][0]
            picked = [by_team[first + team] for team in local]
            arguments[block] = (local, [seed for seed, _ in picked], [team_options for _, team_options in picked])
        results = self.run("reset", arguments)
        return {
            self.team_blocks[block][0] + team: observations
            for block, (local, _, _) in arguments.items()
            for team, observations in zip(local, results[block])
        }

    def step(self, actions: np.ndarray) -> BlockStep:
        """Step every block's teams in an episode with their slots' rows of ``actions`` (checked and finite).

        :return: the arrays of every slot, and the ended episodes with their teams and slots numbered over all blocks
        """
        starts = self.team_starts
        rows = [actions[starts[teams[0]] : starts[teams[-1] + 1]] for teams in self.team_blocks]
        for block, shared in self.shared.items():
            shared["actions"][...] = rows[block]
        results = self.run("step", {0: (rows[0],), **{block: () for block in self.shared}}, "step_shared")
        steps: list[BlockStep] = [results[0]] + [
            BlockStep(*(shared[field] for field in ARRAY_FIELDS), results[block])  # type: ignore[call-arg, arg-type]  # mypy cannot count a star argument's items
            for block, shared in self.shared.items()
        ]
        episodes = []
        for teams, block_step in zip(self.team_blocks, steps):
            first_team, first_slot = teams[0], int(starts[teams[0]])
            for ended in block_step.episodes:
                episodes.append(ended._replace(team=first_team + ended.team, first_slot=first_slot + ended.first_slot))
        if len(steps) == 1:
            return steps[0]
        # copies the shared arrays, which the next step overwrites
        return BlockStep(*(np.concatenate([getattr(block, field) for block in steps]) for field in ARRAY_FIELDS), episodes)  # type: ignore[call-arg, arg-type]  # mypy cannot count a star argument's items

    def close(self) -> None:
        for block in self.blocks:
            block.close()
        for shared in self.shared.values():
            shared.close()
