"""FormationVecEnv: SB3's VecEnv contract with one slot per agent and many teams."""

from __future__ import annotations

import numpy as np
import pytest

from sb3_formation import FormationConfig, FormationEnv, Scenario
from sb3_formation.sb3.vec_env import FormationVecEnv

N_AGENTS = 6


def hexagon(centroid: tuple[float, float]) -> np.ndarray:
    angles = np.deg2rad(np.arange(N_AGENTS) * 60.0 - 90.0)
    return np.asarray(centroid) + np.stack([np.cos(angles), np.sin(angles)], axis=1)


def rollout(venv: FormationVecEnv, steps: int, seed: int) -> list[tuple]:
    rng = np.random.default_rng(seed)
    history = [venv.reset()]
    for _ in range(steps):
        observations, rewards, dones, infos = venv.step(rng.uniform(-1, 1, (venv.num_envs, 2)))
        history.append((observations, rewards, dones, [info.get("TimeLimit.truncated") for info in infos]))
    return history


def test_slot_k_is_agent_k_mod_n_of_team_k_div_n() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    venv = FormationVecEnv(config, n_envs=3)
    venv.seed(40)
    observations = venv.reset()
    assert observations.shape == (3 * N_AGENTS, 211) and venv.num_envs == 18
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (18, 2))
    stepped, rewards, _, _ = venv.step(actions)
    for team in range(3):
        env = FormationEnv(config)
        reset_observations, _ = env.reset(seed=40 + team * N_AGENTS)  # SB3 gives slot k the seed 40 + k
        team_actions = {f"agent_{i}": actions[team * N_AGENTS + i] for i in range(N_AGENTS)}
        step_observations, step_rewards, *_ = env.step(team_actions)
        for agent in range(N_AGENTS):
            slot = team * N_AGENTS + agent
            assert observations[slot].tobytes() == reset_observations[f"agent_{agent}"].tobytes()
            assert stepped[slot].tobytes() == step_observations[f"agent_{agent}"].tobytes()
            assert rewards[slot] == np.float32(step_rewards[f"agent_{agent}"])
    assert not np.array_equal(observations[0], observations[N_AGENTS])  # teams draw different scenarios


def test_time_out_gives_terminal_observation_and_truncated_flag() -> None:
    config = FormationConfig.task("ch4-individual", stage=2, max_steps=5)
    venv = FormationVecEnv(config, n_envs=2)
    venv.seed(1)
    venv.reset()
    twin = FormationEnv(config)
    twin.reset(seed=1)
    rng = np.random.default_rng(2)
    for step in range(1, 6):
        actions = rng.uniform(-1, 1, (venv.num_envs, 2))
        observations, _, dones, infos = venv.step(actions)
        twin_observations, *_ = twin.step({f"agent_{i}": actions[i] for i in range(3)})
        assert dones.tolist() == [step == 5] * 6
    for slot in range(3):
        assert infos[slot]["TimeLimit.truncated"] is True
        assert infos[slot]["terminal_observation"].tobytes() == twin_observations[f"agent_{slot}"].tobytes()
    # the returned observation is the first of the next episode: step counter back to 0
    time_step = venv.observation_layout["time_step"].start
    assert observations[:, time_step].tolist() == [0.0] * 6
    assert infos[0]["episode"]["l"] == 5 and "episode" not in infos[1]


def test_goal_reached_terminates_without_truncated_flag() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    venv = FormationVecEnv(config, n_envs=2)
    scenario = Scenario(hexagon((5.0, 5.0)), (5.41, 5.0))  # one step of +x brings the centroid within eta_g
    venv.set_options([{"scenario": scenario}] * N_AGENTS + [{}] * N_AGENTS)
    venv.reset()
    actions = np.zeros((12, 2))
    actions[:N_AGENTS, 0] = 1.0
    _, _, dones, infos = venv.step(actions)
    assert dones.tolist() == [True] * 6 + [False] * 6
    assert all(info["TimeLimit.truncated"] is False for info in infos[:N_AGENTS])
    assert infos[0]["is_success"] is True and infos[0]["formation_episode"]["success"] is True
    assert infos[0]["episode"]["l"] == 1
    assert "terminal_observation" not in infos[N_AGENTS]


def test_same_seed_same_rollout_and_workers_match_one_process() -> None:
    config = FormationConfig.task("ch5-angle", stage=1, max_steps=40)
    results = []
    for workers in (1, 1, 2):
        venv = FormationVecEnv(config, n_envs=3, n_workers=workers)
        venv.seed(9)
        results.append(rollout(venv, 90, seed=5))
        venv.close()
    for other in results[1:]:
        assert results[0][0].tobytes() == other[0].tobytes()
        for (obs_a, rew_a, done_a, trunc_a), (obs_b, rew_b, done_b, trunc_b) in zip(results[0][1:], other[1:]):
            assert obs_a.tobytes() == obs_b.tobytes() and rew_a.tobytes() == rew_b.tobytes()
            assert done_a.tolist() == done_b.tolist() and trunc_a == trunc_b


def test_env_method_and_set_attr_reach_the_teams_of_the_slots() -> None:
    venv = FormationVecEnv(FormationConfig.task("ch5-bearing", stage=1), n_envs=3)
    assert venv.get_attr("stage") == [1] * 18
    venv.env_method("set_stage", 3, indices=[7])  # slot 7 is agent 1 of team 1
    assert venv.get_attr("stage") == [1] * 6 + [3] * 6 + [1] * 6
    venv.env_method("set_stage", 2)
    assert venv.get_attr("stage", indices=[0, 17]) == [2, 2]
    venv.set_attr("render_lidar", True, indices=[12])
    assert venv.get_attr("render_lidar") == [False] * 12 + [True] * 6
    assert venv.env_is_wrapped(object) == [False] * 18


def test_episode_statistics_are_counted_once_per_team() -> None:
    venv = FormationVecEnv(FormationConfig.task("ch5-bearing", stage=3, max_steps=4), n_envs=3)
    venv.seed(0)
    venv.reset()
    episodes = []
    for _ in range(8):
        _, _, _, infos = venv.step(np.zeros((18, 2)))
        episodes += [(slot, info["episode"]) for slot, info in enumerate(infos) if "episode" in info]
    assert [slot for slot, _ in episodes] == [0, 6, 12, 0, 6, 12]  # two episodes per team, not per agent
    assert all(episode["l"] == 4 for _, episode in episodes)


def test_episode_summary_matches_the_steps() -> None:
    config = FormationConfig.task("ch4-individual", stage=3, max_steps=6)
    venv = FormationVecEnv(config, n_envs=1)
    venv.seed(3)
    venv.reset()
    rng = np.random.default_rng(3)
    returns, angle_errors = [], []
    for _ in range(6):
        _, rewards, _, infos = venv.step(rng.uniform(-1, 1, (3, 2)))
        returns.append(rewards.mean(dtype=np.float64))
        angle_errors.append(np.mean([info["angle_error_deg"] for info in infos]))
    summary = infos[0]["formation_episode"]
    assert summary["length"] == 6 and summary["stage"] == 3 and summary["success"] is False
    assert summary["angle_error_deg"] == pytest.approx(np.mean(angle_errors))
    assert infos[0]["episode"]["r"] == pytest.approx(sum(returns), rel=1e-6)


def test_team_observations_hold_the_whole_team() -> None:
    config = FormationConfig.task("ch4-team")
    venv = FormationVecEnv(config, n_envs=2, team_observations=True)
    observations = venv.reset()
    assert observations.shape == (6, 211 * 4)
    own = observations[:, :211]
    for slot in range(6):
        team = slot // 3
        np.testing.assert_array_equal(observations[slot, 211:].reshape(3, 211), own[team * 3 : team * 3 + 3])


def test_render_tiles_the_teams() -> None:
    venv = FormationVecEnv(FormationConfig.task("ch5-bearing"), n_envs=2, render_mode="rgb_array")
    venv.reset()
    frames = venv.get_images()
    assert len(frames) == 2 and frames[0].shape == (600, 900, 3)
    tiled = venv.render()
    assert tiled.shape == (1200, 900, 3) or tiled.shape == (600, 1800, 3)


def test_bad_actions_and_arguments_name_the_problem() -> None:
    venv = FormationVecEnv(FormationConfig.task("ch5-bearing"), n_envs=2)
    venv.reset()
    actions = np.zeros((12, 2))
    actions[8, 1] = np.nan  # slot 8 = agent 2 of team 1
    with pytest.raises(ValueError, match=r"team 1: action of agent_2 is not finite"):
        venv.step(actions)
    # every team's actions are checked before any team steps: team 0 has not moved
    assert venv.get_attr("step_count", [0])[0] == 0
    rows = "one row per slot"
    with pytest.raises(ValueError, match=rf"actions must have shape \(12, 2\), {rows}, got \(2, 12\)"):
        venv.step(np.zeros((2, 12)))  # 24 numbers, but not one row per slot
    with pytest.raises(ValueError, match=rf"actions must have shape \(12, 2\), {rows}, got \(11, 2\)"):
        venv.step(np.zeros((11, 2)))
    for bad, kind in [(None, "NoneType"), ({"agent_0": [0, 0]}, "dict"), (np.zeros((12, 2), complex), "dtype complex128")]:
        with pytest.raises(ValueError, match=f"actions must be an array of real numbers of shape \\(12, 2\\), got {kind}"):
            venv.step(bad)
    assert venv.get_attr("step_count", [0])[0] == 0
    flat = np.linspace(-1, 1, 24)
    twin = FormationVecEnv(FormationConfig.task("ch5-bearing"), n_envs=2)
    venv.seed(3), twin.seed(3)
    venv.reset(), twin.reset()
    assert venv.step(flat)[0].tobytes() == twin.step(flat.reshape(12, 2))[0].tobytes()  # the documented flat form
    with pytest.raises(ValueError, match="n_workers"):
        FormationVecEnv(FormationConfig.task("ch5-bearing"), n_envs=2, n_workers=3)
    with pytest.raises(ValueError, match="n_envs"):
        FormationVecEnv(FormationConfig.task("ch5-bearing"), n_envs=0)


def test_worker_errors_leave_the_other_workers_in_step() -> None:
    venv = FormationVecEnv(FormationConfig.task("ch5-bearing", stage=2), n_envs=2, n_workers=2)
    venv.seed(0)
    first = venv.reset()
    actions = np.zeros((12, 2))
    actions[1, 0] = np.nan  # team 0, in the first worker
    with pytest.raises(ValueError, match="team 0: action of agent_1 is not finite"):
        venv.step(actions)
    assert venv.get_attr("stage") == [2] * 12  # no stale reply of the second worker is read here
    venv.seed(0)
    assert venv.reset().tobytes() == first.tobytes()
    venv.blocks.blocks[1].process.kill()
    venv.blocks.blocks[1].process.join()
    with pytest.raises(RuntimeError, match=r"worker \(pid \d+\) died"):
        venv.step(np.zeros((12, 2)))
    venv.close()
    venv.close()  # a second close is harmless


def test_teams_of_several_sizes_share_one_rollout_each_team_as_its_own_env() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3, observe_reference_bearings=True)
    venv = FormationVecEnv(config, n_envs=3, team_sizes=[3, 5])  # sizes in turn: 3, 5, 3
    assert venv.num_envs == 11 and [venv.team_slots(team) for team in range(3)] == [slice(0, 3), slice(3, 8), slice(8, 11)]
    venv.seed(40)
    observations = venv.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, (11, 2))
    stepped, rewards, _, _ = venv.step(actions)
    for first, size in [(0, 3), (3, 5), (8, 3)]:
        env = FormationEnv(config.replace(n_agents=size))
        reset_observations, _ = env.reset(seed=40 + first)  # SB3 gives slot k the seed 40 + k; a team its first slot's
        step_observations, step_rewards, *_ = env.step({f"agent_{i}": actions[first + i] for i in range(size)})
        for agent in range(size):
            assert observations[first + agent].tobytes() == reset_observations[f"agent_{agent}"].tobytes()
            assert stepped[first + agent].tobytes() == step_observations[f"agent_{agent}"].tobytes()
            assert rewards[first + agent] == np.float32(step_rewards[f"agent_{agent}"])
    assert venv.get_attr("config", [2, 3])[0].n_agents == 3 and venv.get_attr("config", [3])[0].n_agents == 5
    workers = FormationVecEnv(config, n_envs=3, team_sizes=[3, 5], n_workers=2)
    workers.seed(40)
    assert workers.reset().tobytes() == observations.tobytes()
    assert workers.step(actions)[0].tobytes() == stepped.tobytes()
    workers.close()


def test_teams_of_several_sizes_refuse_a_team_critic_and_bad_sizes() -> None:
    config = FormationConfig.task("ch5-bearing")
    with pytest.raises(ValueError, match=r"team critic\) need teams of one size, got team_sizes \[3, 4\]"):
        FormationVecEnv(config, n_envs=2, team_sizes=[3, 4], team_observations=True)
    with pytest.raises(ValueError, match="n_agents=2 is invalid"):
        FormationVecEnv(config, n_envs=2, team_sizes=[3, 2])
    with pytest.raises(ValueError, match="at least one team size"):
        FormationVecEnv(config, n_envs=2, team_sizes=[])


def test_step_wait_without_step_async_is_named() -> None:
    venv = FormationVecEnv(FormationConfig(n_agents=3), 1)
    venv.reset()
    with pytest.raises(RuntimeError, match=r"step_wait\(\) without step_async\(\)"):
        venv.step_wait()
    venv.step_async(np.zeros((3, 2)))
    venv.step_wait()
    with pytest.raises(RuntimeError, match=r"step_wait\(\) without step_async\(\)"):  # its actions were used once
        venv.step_wait()
    venv.close()
