"""Batched stepping (issue 17, point 1): ``FormationBatch``, and ``FormationVecEnv`` built on it, give bit for bit
what ``FormationEnv.step_array`` gives team by team, over whole episodes with resets."""

from __future__ import annotations

import numpy as np
import pytest

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.batch import FormationBatch
from sb3_formation.env.config import INFO_KEYS
from sb3_formation.env.episodes import EpisodeStatistics
from sb3_formation.sb3.vec_env import FormationVecEnv, slot_observations

PRESETS = ["ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing"]
SIZES = list(range(3, 17))


def wide_actions(rng: np.random.Generator, slots: int) -> np.ndarray:
    """Random actions, a third of them beyond [-1, 1], so that agents collide and clipping is exercised."""
    return rng.normal(0.0, 1.5, (slots, 2))


@pytest.mark.parametrize("preset", PRESETS)
def test_batched_teams_match_the_single_team_env_bit_for_bit(preset: str) -> None:
    """Teams of sizes 3 to 16 in one batch against the same teams stepped alone; every output is compared after the
    step's resets, so no output may share memory that a reset overwrites."""
    configs = [FormationConfig.preset(preset, stage=3, max_steps=25, n_agents=n) for n in SIZES]
    batch = FormationBatch([FormationEnv(config) for config in configs])
    references = [FormationEnv(config) for config in configs]
    statistics = [EpisodeStatistics() for _ in configs]
    for team, reference in enumerate(references):
        expected, _ = reference.reset(seed=10 + team)
        assert np.array_equal(batch.reset_team(team, seed=10 + team), np.stack(list(expected.values())))
    rng = np.random.default_rng(0)
    ends = contacts = 0
    for _ in range(60):
        actions = np.clip(wide_actions(rng, int(batch.starts[-1])), -1.0, 1.0)
        observations, rewards, terminated, truncated, values = batch.step(actions)
        infos = batch.infos(values, terminated)
        expected = [reference.step_array(actions[batch.team_rows(team)]) for team, reference in enumerate(references)]
        for team, (reference, outcome) in enumerate(zip(references, expected)):
            statistics[team].add(outcome[1], outcome[4])
            if outcome[2] or outcome[3]:
                ends += 1
                assert batch.episode_summary(team, outcome[2]) == statistics[team].summary(outcome[2], reference.stage)
                restarted, _ = reference.reset()
                statistics[team].reset()
                assert np.array_equal(batch.reset_team(team), np.stack(list(restarted.values())))
        for team, outcome in enumerate(expected):
            rows = batch.team_rows(team)
            assert np.array_equal(observations[rows], outcome[0])
            assert np.array_equal(rewards[rows], outcome[1])
            assert (terminated[team], truncated[team]) == outcome[2:4]
            assert infos[rows] == outcome[4] and all(list(info) == list(INFO_KEYS) for info in infos[rows])
            contacts += sum(info["collisions_agent"] + info["collisions_obstacle"] for info in outcome[4])
    assert ends >= 2 * len(SIZES) and contacts > 0  # every team ended and restarted at least twice; agents touched
    # the envs' own state, written back on demand, is the reference's
    for team, reference in enumerate(references):
        batch.sync(team)
        assert np.array_equal(batch.envs[team].state(), reference.state())
        assert np.array_equal(batch.envs[team].team_state().lidar_agents, reference.team_state().lidar_agents)


def reference_vec_step(envs: list[FormationEnv], statistics: list[EpisodeStatistics], actions: np.ndarray) -> tuple:
    """A slot-per-agent VecEnv step done team by team with ``FormationEnv.step_array`` (the path before batching)."""
    observations, rewards, dones, infos, start = [], [], [], [], 0
    for env, episode in zip(envs, statistics):
        n_agents = env.config.n_agents
        team_observations, team_rewards, terminated, truncated, team_infos = env.step_array(
            np.clip(actions[start : start + n_agents], -1.0, 1.0)
        )
        start += n_agents
        episode.add(team_rewards, team_infos)
        if terminated or truncated:
            for info, terminal in zip(team_infos, team_observations):
                info["terminal_observation"] = terminal
                info["TimeLimit.truncated"] = truncated and not terminated
            summary = episode.summary(success=terminated, stage=env.stage)
            team_infos[0].update(episode={"r": summary["return"], "l": summary["length"]}, formation_episode=summary)
            team_infos[0]["is_success"] = terminated
            team_observations = np.stack(list(env.reset()[0].values()))
            episode.reset()
        observations.append(team_observations)
        rewards.append(team_rewards)
        dones.append(np.full(n_agents, terminated or truncated))
        infos += team_infos
    return np.concatenate(observations), np.concatenate(rewards).astype(np.float32), np.concatenate(dones), infos


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_the_vec_env_matches_team_by_team_stepping(workers: int) -> None:
    """Teams of sizes 3 to 16 in one ``FormationVecEnv`` (in this process, or split between it and 1 or 2 worker
    processes) against the same teams stepped one by one: observations, rewards, dones and infos (terminal
    observations and team-episode records) agree, also after the curriculum changes the stage of some teams."""
    config = FormationConfig.preset("ch5-bearing", stage=3, max_steps=25)
    venv = FormationVecEnv(config, n_envs=len(SIZES), n_workers=workers, team_sizes=SIZES, start_method="fork")
    venv.seed(3)
    observations = venv.reset()
    envs = [FormationEnv(config.replace(n_agents=n)) for n in SIZES]
    starts = np.concatenate([[0], np.cumsum(SIZES)])
    expected = np.concatenate([np.stack(list(env.reset(seed=3 + int(start))[0].values())) for env, start in zip(envs, starts)])
    assert np.array_equal(observations, expected)
    statistics = [EpisodeStatistics() for _ in envs]
    rng = np.random.default_rng(1)
    ends = 0
    for step in range(70):
        if step == 30:  # as the curriculum callback does it: the new stage's rewards at once
            venv.env_method("set_stage", 2, indices=[0, int(starts[5])])
            for team in (0, 5):
                envs[team].set_stage(2)
        actions = wide_actions(rng, venv.num_envs)
        observations, rewards, dones, infos = venv.step(actions)
        reference = reference_vec_step(envs, statistics, actions)
        assert np.array_equal(observations, reference[0]) and np.array_equal(rewards, reference[1])
        assert np.array_equal(dones, reference[2])
        for info, expected_info in zip(infos, reference[3]):
            if "episode" in info:
                ends += 1
                assert info.pop("episode").keys() == {"r", "l", "t"} and info["formation_episode"]["stage"] in (2, 3)
                expected_info.pop("episode")
            terminal, expected_terminal = (
                info.pop("terminal_observation", None),
                expected_info.pop("terminal_observation", None),
            )
            assert (terminal is None) == (expected_terminal is None)
            assert terminal is None or np.array_equal(terminal, expected_terminal)
            assert info == expected_info
    assert ends >= 2 * len(SIZES)
    assert venv.get_attr("stage", indices=[0, int(starts[1]), int(starts[5])]) == [2, 3, 2]
    venv.close()


def test_team_observations_are_built_from_the_batch() -> None:
    """With a team critic each slot sees its team's rows after its own, as ``slot_observations`` builds them."""
    config = FormationConfig.preset("ch4-team", stage=3, max_steps=10)
    venv = FormationVecEnv(config, n_envs=2, team_observations=True)
    venv.seed(0)
    venv.reset()
    env = FormationEnv(config)
    env.reset(seed=0)
    for _ in range(12):
        observations, _, _, _ = venv.step(np.full((6, 2), 0.3))
        own = np.stack(list(env.step(dict.fromkeys(env.possible_agents, np.full(2, 0.3)))[0].values()))
        if not env.agents:
            own = np.stack(list(env.reset()[0].values()))
        assert np.array_equal(observations[:3], slot_observations(own, 3, True))


def test_stepping_ended_teams_is_refused() -> None:
    batch = FormationBatch([FormationEnv(FormationConfig.preset("ch4-individual", max_steps=1))])
    with pytest.raises(RuntimeError, match="ended teams \\[0\\]"):
        batch.step(np.zeros((3, 2)))  # never reset
    batch.reset_team(0, seed=0)
    batch.step(np.zeros((3, 2)))
    with pytest.raises(RuntimeError, match="reset them first"):
        batch.step(np.zeros((3, 2)))


def test_teams_of_another_task_are_refused() -> None:
    with pytest.raises(ValueError, match="share one task"):
        FormationBatch(
            [FormationEnv(FormationConfig.preset("ch4-individual")), FormationEnv(FormationConfig.preset("ch5-bearing"))]
        )
