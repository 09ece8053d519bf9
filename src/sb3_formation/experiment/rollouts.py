"""Playing episodes: the package's one episode loop, with any policy, on the stepping engine.

Evaluation, videos and ``sb3-formation rollout`` all play through :func:`play_episodes`. Episode k of a job with seed
s is played from ``reset(seed=s + k)``, so every policy played with the same seed meets the same scenarios (start,
goal, obstacles) whatever the number of teams or processes. The policy is any
:class:`~sb3_formation.controllers.base.TeamPolicy` (a trained model with its normaliser, a controller): it gets the
env's raw observations and decides itself what to do with them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch

from sb3_formation.controllers.base import PrivilegedPolicy, TeamPolicy
from sb3_formation.env.blocks import EngineBlocks
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbances import Disturbances
from sb3_formation.env.disturbed import MessageChannel
from sb3_formation.env.engine import InfoColumn
from sb3_formation.env.scenes import scenes_named
from sb3_formation.env.state import TeamState
from sb3_formation.experiment.trajectories import EpisodeRecorder
from sb3_formation.utils.interrupts import raise_if_interrupted


@dataclass
class PlayJob:
    """Episodes to play, and the policy that acts in them.

    :param policy: the policy, already fitted to ``config``
    :param config: task configuration of the episodes
    :param seed: episode k is played from ``reset(seed=seed + k)``
    :param episodes: the episode indices to play
    :param n_envs: teams played at once
    :param deterministic: ask the policy for its noise-free actions
    :param record: record every step of the episodes with an index below this
    :param n_workers: processes stepping the teams, this one included
    """

    policy: TeamPolicy
    config: FormationConfig
    seed: int
    episodes: list[int]
    n_envs: int
    deterministic: bool
    record: int
    n_workers: int = 1


def episode_config(config: FormationConfig, env_overrides: dict[str, Any] | None, stage: int) -> FormationConfig:
    """The task episodes are played in: a policy's task ``config`` with ``env_overrides`` and ``stage``, in the ideal
    world unless the overrides give disturbances (whatever the policy was trained under)."""
    return config.replace(**{"disturbances": Disturbances(), **(env_overrides or {}), "stage": stage})


def play_episodes(
    job: PlayJob,
    on_episode: Callable[[], object] | None = None,
    on_step: Callable[[TeamState, int], None] | None = None,
) -> tuple[list[dict[str, Any]], list[tuple[int, EpisodeRecorder, bool]]]:
    """Play ``job.episodes`` on ``job.n_envs`` teams; a team that ends an episode starts the next one left (teams in
    order), and a team left without one is no longer stepped.

    This is the package's one episode loop: evaluation, videos and ``sb3-formation rollout`` all play through it. The
    teams are stepped by :class:`~sb3_formation.env.blocks.EngineBlocks` without automatic resets; the policy sees
    every team's observations in one batch (a team without an episode keeps its last ones).

    :param on_episode: called after each episode
    :param on_step: called with (team state, episode) after each reset and each step (every team in this process:
        ``n_workers`` must be 1)
    :return: one row per episode (in the order they ended), and (episode, recorder, success) of recorded episodes
    """
    config, n_agents = job.config, job.config.n_agents
    unit = scenes_named(config.scenes).formations  # the formations of a crossing start together
    if len(job.episodes) % unit:
        raise ValueError(
            f"the {config.scenes!r} scenes fly {unit} formations together, an episode each: play a multiple of "
            f"{unit} episodes, got {len(job.episodes)}"
        )
    n_teams = unit * -(-job.n_envs // unit)
    if on_step is not None and job.n_workers > 1:
        raise ValueError("on_step reads every team in this process: play with n_workers=1")
    blocks = EngineBlocks([config] * n_teams, min(job.n_workers, n_teams // unit), auto_reset=False)
    privileged = isinstance(job.policy, PrivilegedPolicy)  # it reads each team's map when its episode starts
    # a privileged policy that reads every team's state before every step (controller:crowd)
    observe: Callable[[list[int], list[TeamState]], None] | None = getattr(job.policy, "observe_states", None)
    # what a policy reports of an episode of its own (a filtered policy: what its filter did), by the team's rows
    metrics: Callable[[slice], dict[str, float]] | None = getattr(job.policy, "episode_metrics", None)
    queue = list(reversed(job.episodes))
    current: list[int | None] = [None] * n_teams
    seeds = [0] * n_teams  # the seed each team's episode was drawn from (a crossing's: its first team's)
    recorders: list[EpisodeRecorder | None] = [None] * n_teams
    observations = np.zeros((n_teams * n_agents, blocks.local.engine.observation_dim), np.float32)
    # a talking policy's messages cross the task's links (they lose and delay them unless the task is ideal)
    communication = config.disturbances.communication
    lossy = getattr(job.policy, "message_size", 0) and not communication.is_ideal
    channel = MessageChannel(communication, n_agents, n_teams) if lossy else None
    links: dict[str, Any] = {} if channel is None else {"channel": channel}
    failing = not config.disturbances.failures.is_ideal  # the policy is told which agents still fly
    flying = np.ones(n_teams * n_agents, dtype=bool)
    if failing:
        links["flying"] = flying
    episode_starts = np.ones(n_teams * n_agents, dtype=bool)
    rows: list[dict[str, Any]] = []
    recorded: list[tuple[int, EpisodeRecorder, bool]] = []

    def slots(team: int) -> slice:
        return slice(team * n_agents, (team + 1) * n_agents)

    def start(teams: list[int]) -> None:
        """Give each of ``teams`` the next episode left, in order, and reset them; in a crossing, a unit's teams wait
        until all of them ended, then take the next episodes together, drawn from the first one's seed."""
        started: list[int] = []
        for team in teams:
            current[team] = None
        for first in sorted({team - team % unit for team in teams}):
            members = list(range(first, first + unit))
            if queue and all(current[team] is None for team in members):
                for team in members:
                    current[team] = queue.pop()
                    seeds[team] = job.seed + cast(int, current[first])  # (an int: mypy does not narrow list items)
                started += members
        if not started:
            return
        reset = blocks.reset(started, [seeds[team] if team % unit == 0 else None for team in started], [None] * len(started))
        every = on_step is not None or privileged or failing
        watched = started if every else [t for t in started if cast(int, current[t]) < job.record]
        states = blocks.call_teams("team_states", watched) if watched else {}
        if privileged:  # the map, for a policy that reads it
            cast(PrivilegedPolicy, job.policy).start_episodes(started, [states[team] for team in started])
        for team in started:
            observations[slots(team)] = reset[team]
            if failing:  # an agent may fail at step 0
                flying[slots(team)] = True if states[team].flying is None else states[team].flying
            if channel is not None:
                channel.start(team, job.seed + cast(int, current[team]))
            episode_starts[slots(team)] = True
            recorders[team] = EpisodeRecorder(states[team]) if cast(int, current[team]) < job.record else None
            if on_step is not None:
                on_step(states[team], cast(int, current[team]))

    try:
        start(list(range(n_teams)))
        states = None
        while any(episode is not None for episode in current):
            raise_if_interrupted()  # a Ctrl-C that landed in a finaliser was dropped there
            playing = [team for team, episode in enumerate(current) if episode is not None]
            if observe is not None:
                now = blocks.call_teams("team_states", playing)
                observe(playing, [now[team] for team in playing])
            actions, states = job.policy.predict(
                observations, state=states, episode_start=episode_starts, deterministic=job.deterministic, **links
            )
            actions = blocks.checked_actions(np.asarray(actions).reshape(n_teams * n_agents, 2), playing)
            episode_starts[:] = False
            step = blocks.step(actions)
            flying[:] = step.flying
            for team in playing:
                if recorders[team] is not None:
                    cast(EpisodeRecorder, recorders[team]).add(step, slots(team), actions)
                if on_step is not None:
                    on_step(blocks.local.engine.team_state(team), cast(int, current[team]))  # a playing team's
            ended = {episode.team: episode for episode in step.episodes}
            for team in playing:
                if team not in ended:
                    observations[slots(team)] = step.observations[slots(team)]
                    continue
                episode = ended[team]
                summary = dict(episode.summary)
                terms = summary.pop("reward_terms")
                rows.append(
                    {
                        "episode": current[team],
                        "seed": seeds[team],
                        "team": team,
                        **summary,
                        "comm_exceeded_fraction": episode.comm_exceeded_steps / summary["length"],
                        "final_goal_distance": float(step.info_values[episode.first_slot, InfoColumn.GOAL_DISTANCE]),
                        **{f"reward_{name}": value for name, value in terms.items()},
                        **(metrics(slots(team)) if metrics is not None else {}),
                    }
                )
                if recorders[team] is not None:
                    recorded.append((cast(int, current[team]), cast(EpisodeRecorder, recorders[team]), episode.success))
                if on_episode is not None:
                    on_episode()
            start(sorted(ended))
    finally:
        blocks.close()
    return rows, recorded


def seed_policy(policy: TeamPolicy, seed: int) -> None:
    """Seed what a policy samples from: torch's generator (SB3 policies sample with it) and the policy's own ``seed``."""
    torch.manual_seed(seed)
    if hasattr(policy, "seed"):
        policy.seed(seed)
