"""``FormationVecEnv``: many teams of a :class:`FormationEnv` as one SB3 ``VecEnv`` with one slot per agent.

The teams' agents take the slots one team after the other (slot k is agent ``k % n`` of team ``k // n`` when every
team has n agents), so one SB3 ``PPO`` shares its parameters across every agent of every team, whatever its size.
All slots of a team end together and are reset in the same step, as SB3 expects of a ``VecEnv``. The teams are
stepped by :class:`~sb3_formation.env.blocks.EngineBlocks` (the engine, in one or more processes).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn

from sb3_formation.env.blocks import EngineBlocks
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import agent_infos


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
      one worker process each of the others, all at once (:class:`~sb3_formation.env.blocks.EngineBlocks`). Each team
      is independent, so the same seed gives the same rollouts for any ``n_workers``.

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
        self.blocks = EngineBlocks(self.team_configs, n_workers, team_observations, True, render_mode, start_method)
        self._team_starts = self.blocks.team_starts  # team j: slots starts[j]:starts[j + 1]
        self._slot_teams = np.repeat(np.arange(n_envs), [team_config.n_agents for team_config in self.team_configs])
        probe = self.blocks.local.envs[0]
        agent_space = probe.observation_space(probe.possible_agents[0])
        self.agent_observation_dim = agent_space.shape[0]
        self.binary_observation_mask = probe.binary_observation_mask
        self.observation_layout = probe.observation_layout
        blocks = 1 + self.team_configs[0].n_agents if team_observations else 1
        observation_space = gymnasium.spaces.Box(np.tile(agent_space.low, blocks), np.tile(agent_space.high, blocks))
        self._actions: np.ndarray | None = None
        super().__init__(int(self._team_starts[-1]), observation_space, probe.action_space(probe.possible_agents[0]))

    # Slot and team bookkeeping -----------------------------------------------------------------------------------

    def team_slots(self, team: int) -> slice:
        """The slots of a team's agents, agent 0 first."""
        return slice(int(self._team_starts[team]), int(self._team_starts[team + 1]))

    def slot_team(self, slot: int) -> int:
        """The team whose agent fills ``slot``."""
        return int(self._slot_teams[slot])

    def slots_by_task(self) -> dict[FormationConfig, np.ndarray]:
        """The slots of each team task's teams (whole teams, agent 0 first), by task (they differ in ``n_agents``)."""
        slots: dict[FormationConfig, list[int]] = {}
        for team, config in enumerate(self.team_configs):
            slots.setdefault(config, []).extend(range(self.num_envs)[self.team_slots(team)])
        return {config: np.array(team_slots) for config, team_slots in slots.items()}

    def _teams_of(self, indices: VecEnvIndices) -> list[int]:
        """Teams of the given slots, in order of first appearance."""
        return list(dict.fromkeys(int(self._slot_teams[slot]) for slot in self._get_indices(indices)))

    # VecEnv interface --------------------------------------------------------------------------------------------

    def reset(self) -> VecEnvObs:
        firsts = self._team_starts
        teams = range(self.n_teams)
        seeds = [self._seeds[firsts[team]] for team in teams]
        observations = self.blocks.reset(teams, seeds, [self._options[firsts[team]] for team in teams])
        self._reset_seeds()
        self._reset_options()
        return np.concatenate([observations[team] for team in teams])

    def checked_actions(self, actions: Any) -> np.ndarray:
        """The slots' actions as a ``(num_envs, 2)`` float64 array, checked before any team steps
        (:meth:`~sb3_formation.env.blocks.EngineBlocks.checked_actions`).

        :param actions: ``(num_envs, 2)`` real numbers, one row per slot (or the same flattened, ``(num_envs * 2,)``)
        :raises ValueError: another shape, a value that is not a real number, or one that is not finite (naming its
            team and agent)
        """
        return self.blocks.checked_actions(actions)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = self.checked_actions(actions)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async(): give the actions with step_async(actions) first")
        actions, self._actions = self._actions, None
        step = self.blocks.step(actions)
        infos = agent_infos(step.info_values, step.contacts, step.success)
        for ended in step.episodes:
            slot = ended.first_slot
            for offset, terminal in enumerate(ended.terminal_observations):
                infos[slot + offset]["terminal_observation"] = terminal
                infos[slot + offset]["TimeLimit.truncated"] = ended.timed_out
            infos[slot].update(episode=ended.episode, is_success=ended.success, formation_episode=ended.summary)
        return step.observations, step.rewards.astype(np.float32), step.dones, infos

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        slots = list(self._get_indices(indices))
        values = self.blocks.call_teams("get_attr", self._teams_of(slots), attr_name)
        return [values[self._slot_teams[slot]] for slot in slots]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self.blocks.call_teams("set_attr", self._teams_of(indices), attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        slots = list(self._get_indices(indices))
        values = self.blocks.call_teams("env_method", self._teams_of(slots), method_name, method_args, method_kwargs)
        return [values[self._slot_teams[slot]] for slot in slots]

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One frame per team (not per slot), which ``render()`` tiles."""
        frames = self.blocks.run("get_images", {block: () for block in range(len(self.blocks.blocks))})
        return [frame for block in range(len(self.blocks.blocks)) for frame in frames[block]]

    def close(self) -> None:
        self.blocks.close()


def uses_team_critic(config: FormationConfig, team_critic: bool | None = None) -> bool:
    """Whether a policy of ``config`` has the team critic (fig. 4.3), whose slots observe their whole team: as
    ``team_critic`` says, else (``None``) exactly when the task uses the team reward (eqs 27-32).

    :param config: the task
    :param team_critic: the choice, or ``None`` for the task's
    """
    return config.team_reward if team_critic is None else team_critic


def make_formation_vec_env(
    task: str | FormationConfig = "ch5-bearing",
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
    """The one call a notebook needs: ``n_envs`` teams of a thesis task as an SB3 ``VecEnv``, one slot per agent.

    :param task: ``"ch4-individual"``, ``"ch4-team"``, ``"ch5-angle"`` or ``"ch5-bearing"``
        (:data:`~sb3_formation.env.config.TASKS`), or a whole :class:`FormationConfig`
    :param n_envs: number of teams (the thesis trained 12 in chapter 4 and 14 in chapter 5: see the recipes)
    :param n_agents: team size (default: the task's)
    :param stage: curriculum stage (default: the task's, 1)
    :param seed: seed of the teams' scenario generators (each team gets ``seed`` + its first slot); ``None``: random
    :param n_workers: processes stepping the teams, this one included
    :param normalize: wrap in :class:`~sb3_formation.sb3.normalization.ScaleNormalizeVecEnv`
    :param team_critic: give every slot its team's observations (default: when the task uses the team reward,
        :func:`uses_team_critic`)
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
    config = task.replace(**overrides) if isinstance(task, FormationConfig) else FormationConfig.task(task, **overrides)
    venv = FormationVecEnv(
        config,
        n_envs=n_envs,
        team_observations=uses_team_critic(config, team_critic),
        n_workers=n_workers,
        render_mode=render_mode,
        team_sizes=team_sizes,
    )
    if seed is not None:
        venv.seed(seed)
    if normalize:
        return ScaleNormalizeVecEnv(venv, venv.agent_observation_dim, venv.binary_observation_mask)
    return venv
