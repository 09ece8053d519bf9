"""``FormationVecEnv``: many teams of a :class:`FormationEnv` as one SB3 ``VecEnv`` with one slot per agent.

The teams' agents take the slots one team after the other (slot k is agent ``k % n`` of team ``k // n`` when every
team has n agents), so one SB3 ``PPO`` shares its parameters across every agent of every team, whatever its size.
All slots of a team end together and are reset in the same step, as SB3 expects of a ``VecEnv``.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn

from sb3_formation.env.batch import INFO_VALUES, FormationBatch
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv, agent_infos
from sb3_formation.utils.processes import SharedArrays, WorkerProcess, gather, worker_context

#: seconds a worker process polls for the next step before it sleeps (waking it would cost more than a step), and the
#: VecEnv for a worker's reply; the steps of a rollout follow each other well within it, training phases do not
WORKER_SPIN = 0.02


def slot_observations(own: np.ndarray, n_agents: int, team_observations: bool) -> np.ndarray:
    """The slots' observations from the agents' own ``(teams * n, dim)`` observations (row k: agent ``k % n`` of team
    ``k // n``).

    :param own: the agents' own observations, whole teams one after the other
    :param n_agents: team size n
    :param team_observations: append the whole team's observations (agent 0 first) to every row, for a team critic
    :return: ``own``, or ``(teams * n, (1 + n) * dim)``
    """
    if not team_observations:
        return own
    teams = own.reshape(-1, n_agents * own.shape[-1])
    return np.hstack([own, np.repeat(teams, n_agents, axis=0)])


class TeamEpisode(NamedTuple):
    """A team's episode that ended in a step: what the infos of its slots get."""

    first_slot: int  #: within the block
    terminal_observations: np.ndarray
    timed_out: bool
    success: bool
    episode: dict[str, float]  #: SB3's record: team return, length, time
    summary: dict[str, Any]  #: ``formation_episode``


class BlockStep(NamedTuple):
    """One step of a block of teams, as arrays (:meth:`TeamBatch.step`), then the block's ended episodes."""

    observations: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    info_values: np.ndarray
    contacts: np.ndarray
    success: np.ndarray  #: per slot
    episodes: list[TeamEpisode]


#: the :class:`BlockStep` fields that are arrays with a row per slot
ARRAY_FIELDS = BlockStep._fields[:-1]


class TeamBatch:
    """A block of teams stepped in one process: the unit of both the in-process and the worker-process VecEnv.

    The teams step together (:class:`~sb3_formation.env.batch.FormationBatch`); this adds SB3's ``VecEnv``
    conventions: slots, automatic resets, terminal observations and the team-episode infos.

    :param configs: task configuration of each team of this block
    :param team_observations: each slot also sees its whole team's observations (for a team critic)
    :param render_mode: render mode of the teams' envs
    :param shared: the block's ``actions`` and :data:`ARRAY_FIELDS` arrays in shared memory, for
        :meth:`step_shared` (in a worker process)
    """

    def __init__(
        self,
        configs: Sequence[FormationConfig],
        team_observations: bool,
        render_mode: str | None,
        shared: SharedArrays | None = None,
    ) -> None:
        self.batch = FormationBatch([FormationEnv(config, render_mode=render_mode) for config in configs])
        self.envs = self.batch.envs
        self.team_observations = team_observations
        self.shared = shared
        self.start_time = time.time()

    def _slot_observations(self, own: np.ndarray, n_agents: int) -> np.ndarray:
        return slot_observations(own, n_agents, self.team_observations)

    def reset(self, seeds: Sequence[int | None], options: Sequence[dict[str, Any]]) -> np.ndarray:
        """Reset every team; team j with ``seeds[j]`` and ``options[j]``. :return: ``(slots, obs_dim)``"""
        return np.concatenate(
            [
                self._slot_observations(self.batch.reset_team(team, seed, team_options or None), len(env.possible_agents))
                for team, (env, seed, team_options) in enumerate(zip(self.envs, seeds, options))
            ]
        )

    def step(self, actions: np.ndarray) -> BlockStep:
        """Step every team with its agents' rows of ``actions``; teams that end are reset at once.

        :param actions: ``(slots, 2)`` finite actions (checked by the VecEnv), each team's agents one after the other
        :return: the block's arrays; the VecEnv builds the info dicts from them in its own process (pickling dicts
            between processes would cost more than the step)
        """
        batch = self.batch
        observations, rewards, terminated, truncated, values = batch.step(np.minimum(np.maximum(actions, -1.0), 1.0))
        contacts = batch.contacts.copy()  # before the resets below clear the ended teams' rows
        observations = self._slot_observations(observations, int(batch.sizes[0]))  # team critics: teams of one size
        ended = terminated | truncated
        episodes = []
        for team in np.flatnonzero(ended).tolist():
            rows = batch.team_rows(team)
            success = bool(terminated[team])
            summary = batch.episode_summary(team, success)
            record = {"r": summary["return"], "l": summary["length"], "t": round(time.time() - self.start_time, 6)}
            terminal = observations[rows].copy()  # the rows get the reset's observations
            episodes.append(TeamEpisode(rows.start, terminal, bool(truncated[team]) and not success, success, record, summary))
            observations[rows] = self._slot_observations(batch.reset_team(team), rows.stop - rows.start)
        dones, success = np.repeat(ended, batch.sizes), np.repeat(terminated, batch.sizes)
        return BlockStep(observations, rewards, dones, values, contacts, success, episodes)

    def step_shared(self) -> list[TeamEpisode]:
        """:meth:`step` with the actions read from ``shared`` and the arrays written to it: only the ended episodes
        (few, and rarely any) go through the worker's pipe."""
        step = self.step(self.shared["actions"])
        for field in ARRAY_FIELDS:
            self.shared[field][...] = getattr(step, field)
        return step.episodes

    def get_attr(self, name: str, teams: Iterable[int]) -> list[Any]:
        """Attribute ``name`` of each of ``teams`` (indices within this block)."""
        return [getattr(self._synced(team), name) for team in teams]

    def set_attr(self, name: str, teams: Iterable[int], value: Any) -> None:
        """Set attribute ``name`` of each of ``teams``."""
        for team in teams:
            setattr(self._synced(team), name, value)
            self.batch.load(team)

    def env_method(self, name: str, teams: Iterable[int], args: tuple, kwargs: dict[str, Any]) -> list[Any]:
        """Call method ``name`` of each of ``teams``."""
        results = []
        for team in teams:
            results.append(getattr(self._synced(team), name)(*args, **kwargs))
            self.batch.load(team)
        return results

    def _synced(self, team: int) -> FormationEnv:
        """A team's env, with the batch's state of it written back."""
        self.batch.sync(team)
        return self.envs[team]

    def get_images(self) -> list[np.ndarray]:
        """One ``rgb_array`` frame per team."""
        return [self._synced(team).render() for team in range(len(self.envs))]

    def close(self) -> None:
        """Close every team's env (and this process's view of the shared arrays)."""
        for env in self.envs:
            env.close()
        if self.shared is not None:
            self.shared.close()


class FormationVecEnv(VecEnv):
    """``n_envs`` teams of a :class:`FormationEnv` as an SB3 ``VecEnv`` with one slot per agent.

    - The teams' agents take the slots one team after the other: with ``config.n_agents`` agents in every team, slot
      k is agent ``k % n`` of team ``k // n``. With ``team_sizes`` the teams have several sizes (their observations
      have the same size, Table 3.1) and one rollout mixes them; every slot has the env's per-agent spaces (with
      ``team_observations`` the observation is [own, then every team member's, agent 0 first], for a team critic,
      so the teams must have one size).
    - All slots of a team end together and are reset in the same step; an ended slot's info has
      ``terminal_observation`` and ``TimeLimit.truncated`` (True exactly for time-outs, so PPO bootstraps them).
    - Seeding: ``seed(s)`` (as ``PPO(seed=s)`` calls it) gives each team the seed SB3 assigns to its first slot,
      ``s + slot``; each team then draws its scenarios from its own generator.
    - ``get_attr``, ``set_attr`` and ``env_method`` reach the teams of the given slots; a call on several slots of
      one team acts once on that team, and results are repeated for each requested slot.
    - Episode statistics are counted once per team: the info of the team's first slot carries ``episode``
      (``r`` = return averaged over the team's agents, ``l`` = length), ``is_success`` and ``formation_episode``
      (means over the episode of the formation errors and reward terms, collision totals, success, stage).
    - With ``n_workers > 1`` the teams are split into ``n_workers`` contiguous blocks: this process steps the first,
      one worker process each of the others, all at once; actions and results go through shared memory, and the
      workers poll for the next step for :data:`WORKER_SPIN` seconds before they sleep. Each team is independent, so
      the same seed gives the same rollouts for any ``n_workers``.

    :param config: task configuration of every team
    :param n_envs: number of teams
    :param team_observations: give every slot its whole team's observations (for a team critic)
    :param n_workers: processes stepping the teams, this one included (1: every team in this process)
    :param render_mode: ``None`` or ``"rgb_array"``; ``render()`` tiles the teams' frames
    :param start_method: multiprocessing start method for the workers (default: ``forkserver`` where available)
    :param team_sizes: team sizes (each >= 3) taken in turn: team j has ``team_sizes[j % len(team_sizes)]`` agents
        (default: ``config.n_agents`` for every team)
    """

    def __init__(
        self,
        config: FormationConfig,
        n_envs: int,
        team_observations: bool = False,
        n_workers: int = 1,
        render_mode: str | None = None,
        start_method: str | None = None,
        team_sizes: Sequence[int] | None = None,
    ) -> None:
        if not (isinstance(n_envs, int) and n_envs >= 1):
            raise ValueError(f"n_envs must be an integer >= 1, got {n_envs!r}")
        if not (isinstance(n_workers, int) and 1 <= n_workers <= n_envs):
            raise ValueError(f"n_workers must be an integer in [1, n_envs={n_envs}], got {n_workers!r}")
        sizes = [config.n_agents] if team_sizes is None else list(team_sizes)
        if not sizes:
            raise ValueError("team_sizes must list at least one team size")
        if team_observations and len(set(sizes)) > 1:
            raise ValueError(f"team observations (a team critic) need teams of one size, got team_sizes {sizes}")
        sizes_of = {size: config.replace(n_agents=size) for size in sizes}  # validates every size
        self.config = config
        self.n_teams = n_envs
        #: the task of each team (they differ in n_agents only)
        self.team_configs = [sizes_of[sizes[team % len(sizes)]] for team in range(n_envs)]
        self.team_observations = team_observations
        self.n_workers = n_workers
        team_sizes = [team_config.n_agents for team_config in self.team_configs]
        self._team_starts = np.concatenate([[0], np.cumsum(team_sizes)])  # team j: slots starts[j]:starts[j + 1]
        self._slot_teams = np.repeat(np.arange(n_envs), team_sizes)
        probe = FormationEnv(config)
        agent_space = probe.observation_space(probe.possible_agents[0])
        self.agent_observation_dim = agent_space.shape[0]
        self.binary_observation_mask = probe.binary_observation_mask
        self.observation_layout = probe.observation_layout
        blocks = 1 + team_sizes[0] if team_observations else 1
        observation_space = gymnasium.spaces.Box(np.tile(agent_space.low, blocks), np.tile(agent_space.high, blocks))
        self._team_blocks = [block.tolist() for block in np.array_split(np.arange(n_envs), n_workers)]
        arguments = [
            ([self.team_configs[team] for team in block], team_observations, render_mode) for block in self._team_blocks
        ]
        #: the first block's teams, stepped in this process; the others' in worker processes
        self._batches: list[TeamBatch | WorkerProcess] = [TeamBatch(*arguments[0])]
        #: per worker block: its actions and step arrays in shared memory
        self._shared: dict[int, SharedArrays] = {}
        if n_workers > 1:
            context = worker_context(start_method)
            for block, block_arguments in enumerate(arguments[1:], start=1):
                slots = sum(team_config.n_agents for team_config in block_arguments[0])
                self._shared[block] = shared = SharedArrays(self._step_layout(slots, observation_space.shape[0]))
                worker = WorkerProcess(TeamBatch, (*block_arguments, shared), "FormationVecEnv worker", context, WORKER_SPIN)
                self._batches.append(worker)
        self._actions: np.ndarray | None = None
        super().__init__(int(self._team_starts[-1]), observation_space, probe.action_space(probe.possible_agents[0]))

    @staticmethod
    def _step_layout(slots: int, observation_dim: int) -> dict[str, tuple[tuple[int, ...], Any]]:
        """Shapes and dtypes of a block's actions and :class:`BlockStep` arrays, for ``slots`` slots."""
        return {
            "actions": ((slots, 2), np.float64),
            "observations": ((slots, observation_dim), np.float32),
            "rewards": ((slots,), np.float64),
            "dones": ((slots,), bool),
            "info_values": ((slots, INFO_VALUES), np.float64),
            "contacts": ((slots, 2), np.int64),
            "success": ((slots,), bool),
        }

    # Slot and team bookkeeping -----------------------------------------------------------------------------------

    def team_slots(self, team: int) -> slice:
        """The slots of a team's agents, agent 0 first."""
        return slice(int(self._team_starts[team]), int(self._team_starts[team + 1]))

    def _teams_of(self, indices: VecEnvIndices) -> list[int]:
        """Teams of the given slots, in order of first appearance."""
        return list(dict.fromkeys(int(self._slot_teams[slot]) for slot in self._get_indices(indices)))

    def _per_block(self, teams: Iterable[int]) -> list[tuple[int, list[int]]]:
        """Group global team indices by block: (block index, team indices within the block)."""
        grouped: dict[int, list[int]] = {}
        for team in teams:
            for block, block_teams in enumerate(self._team_blocks):
                if team in block_teams:
                    grouped.setdefault(block, []).append(team - block_teams[0])
        return list(grouped.items())

    def _run(self, command: str, arguments: dict[int, tuple], worker_command: str | None = None) -> dict[int, Any]:
        """Call ``command`` on the blocks in ``arguments`` (block -> arguments), the workers' while this process runs
        its own block's.

        :param worker_command: the workers' command instead of ``command``
        """
        workers = [block for block in arguments if block > 0]
        for block in workers:
            self._batches[block].send(worker_command or command, *arguments[block])
        results = {}
        try:
            if 0 in arguments:
                results[0] = getattr(self._batches[0], command)(*arguments[0])
        finally:  # read the workers' replies even after an error here, so none is left in a pipe
            results.update(zip(workers, gather([self._batches[block] for block in workers], spin=WORKER_SPIN)))
        return results

    def _call_teams(self, command: str, teams: list[int], *data: Any) -> dict[int, Any]:
        """Run ``command(data[0], local_teams, *data[1:])`` on the blocks holding ``teams``; return team -> result."""
        grouped = self._per_block(teams)
        results = self._run(command, {block: (data[0], local, *data[1:]) for block, local in grouped})
        values: dict[int, Any] = {}
        for block, local in grouped:
            block_values = results[block] if results[block] is not None else [None] * len(local)
            values.update(zip((self._team_blocks[block][0] + team for team in local), block_values))
        return values

    # VecEnv interface --------------------------------------------------------------------------------------------

    def reset(self) -> VecEnvObs:
        firsts = self._team_starts
        arguments = {
            block: ([self._seeds[firsts[team]] for team in teams], [self._options[firsts[team]] for team in teams])
            for block, teams in enumerate(self._team_blocks)
        }
        observations = self._run("reset", arguments)
        self._reset_seeds()
        self._reset_options()
        return np.concatenate([observations[block] for block in range(len(self._batches))])

    def checked_actions(self, actions: Any) -> np.ndarray:
        """The slots' actions as a ``(num_envs, 2)`` float64 array, checked before any team steps.

        :param actions: ``(num_envs, 2)`` real numbers, one row per slot (or the same flattened, ``(num_envs * 2,)``)
        :raises ValueError: another shape, a value that is not a real number, or one that is not finite (naming its
            team and agent)
        """
        array = np.asarray(actions) if isinstance(actions, (np.ndarray, list, tuple)) else None
        if array is None or array.dtype.kind not in "iuf":
            kind = type(actions).__name__ if array is None else f"dtype {array.dtype}"
            raise ValueError(f"actions must be an array of real numbers of shape ({self.num_envs}, 2), got {kind}")
        if array.shape == (self.num_envs * 2,):
            array = array.reshape(self.num_envs, 2)
        if array.shape != (self.num_envs, 2):
            raise ValueError(f"actions must have shape ({self.num_envs}, 2), one row per slot, got {array.shape}")
        array = array.astype(np.float64)
        bad = np.flatnonzero(~np.isfinite(array).all(axis=1))
        if bad.size:
            slot = int(bad[0])
            team = int(self._slot_teams[slot])
            agent = slot - int(self._team_starts[team])
            raise ValueError(f"team {team}: action of agent_{agent} is not finite: {array[slot].tolist()}")
        return array

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = self.checked_actions(actions)

    def step_wait(self) -> VecEnvStepReturn:
        starts = self._team_starts
        actions = [self._actions[starts[teams[0]] : starts[teams[-1] + 1]] for teams in self._team_blocks]
        for block, shared in self._shared.items():
            shared["actions"][...] = actions[block]
        results = self._run("step", {0: (actions[0],), **{block: () for block in self._shared}}, "step_shared")
        steps = [results[0]] + [
            BlockStep(*(shared[field] for field in ARRAY_FIELDS), results[block]) for block, shared in self._shared.items()
        ]
        if len(steps) == 1:
            step = steps[0]
        else:  # copies the shared arrays, which the next step overwrites
            step = BlockStep(*(np.concatenate([getattr(block, field) for block in steps]) for field in ARRAY_FIELDS), [])
        infos = agent_infos(step.info_values, step.contacts, step.success)
        for block, block_step in zip(self._team_blocks, steps):
            first = int(starts[block[0]])
            for ended in block_step.episodes:
                slot = first + ended.first_slot
                for offset, terminal in enumerate(ended.terminal_observations):
                    infos[slot + offset]["terminal_observation"] = terminal
                    infos[slot + offset]["TimeLimit.truncated"] = ended.timed_out
                infos[slot].update(episode=ended.episode, is_success=ended.success, formation_episode=ended.summary)
        return step.observations, step.rewards.astype(np.float32), step.dones, infos

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        slots = list(self._get_indices(indices))
        values = self._call_teams("get_attr", self._teams_of(slots), attr_name)
        return [values[self._slot_teams[slot]] for slot in slots]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._call_teams("set_attr", self._teams_of(indices), attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        slots = list(self._get_indices(indices))
        values = self._call_teams("env_method", self._teams_of(slots), method_name, method_args, method_kwargs)
        return [values[self._slot_teams[slot]] for slot in slots]

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One frame per team (not per slot), which ``render()`` tiles."""
        frames = self._run("get_images", {block: () for block in range(len(self._batches))})
        return [frame for block in range(len(self._batches)) for frame in frames[block]]

    def close(self) -> None:
        for batch in self._batches:
            batch.close()
        for shared in self._shared.values():
            shared.close()


def make_formation_vec_env(
    preset: str = "ch5-bearing",
    n_envs: int = 1,
    n_agents: int | None = None,
    stage: int | None = None,
    seed: int | None = None,
    n_workers: int = 1,
    normalize: bool = True,
    team_critic: bool | None = None,
    render_mode: str | None = None,
    team_sizes: Sequence[int] | None = None,
    **config_overrides: Any,
) -> VecEnv:
    """The one call a notebook needs: ``n_envs`` teams of a thesis preset as an SB3 ``VecEnv``, one slot per agent.

    :param preset: ``"ch4-individual"``, ``"ch4-team"``, ``"ch5-angle"`` or ``"ch5-bearing"``
    :param n_envs: number of teams (the thesis trained 12 in chapter 4 and 14 in chapter 5: see the set-ups)
    :param n_agents: team size (default: the preset's)
    :param stage: curriculum stage (default: the preset's, 1)
    :param seed: seed of the teams' scenario generators (each team gets ``seed`` + its first slot); ``None``: random
    :param n_workers: processes stepping the teams, this one included
    :param normalize: wrap in :class:`~sb3_formation.normalization.ScaleNormalizeVecEnv`
    :param team_critic: give every slot its team's observations (default: when the preset uses the team reward)
    :param render_mode: ``None`` or ``"rgb_array"``
    :param team_sizes: teams of several sizes, taken in turn (see :class:`FormationVecEnv`); default: ``n_agents``
    :param config_overrides: further :class:`FormationConfig` fields
    """
    from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv

    overrides = dict(config_overrides)
    if n_agents is not None:
        overrides["n_agents"] = n_agents
    if stage is not None:
        overrides["stage"] = stage
    config = FormationConfig.preset(preset, **overrides)
    team_observations = config.team_reward if team_critic is None else team_critic
    venv = FormationVecEnv(
        config,
        n_envs=n_envs,
        team_observations=team_observations,
        n_workers=n_workers,
        render_mode=render_mode,
        team_sizes=team_sizes,
    )
    if seed is not None:
        venv.seed(seed)
    if normalize:
        return ScaleNormalizeVecEnv(venv, venv.agent_observation_dim, venv.binary_observation_mask)
    return venv
