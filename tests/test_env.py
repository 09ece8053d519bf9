"""FormationEnv: the PettingZoo API, determinism, episode ends, actions, infos, observations and rendering."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from sb3_formation import REWARD_TERMS, FormationConfig, FormationEnv, Scenario
from sb3_formation.env.config import INFO_KEYS


def random_actions(env: FormationEnv, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {agent: rng.uniform(-1, 1, 2).astype(np.float32) for agent in env.agents}


def hexagon_scenario(centroid: tuple[float, float], goal: tuple[float, float], side: float = 1.0) -> Scenario:
    """Six agents on a regular hexagon of the given side around ``centroid``, agent i at angle i * 60 - 90 deg."""
    angles = np.deg2rad(np.arange(6) * 60.0 - 90.0)
    positions = np.asarray(centroid) + side * np.stack([np.cos(angles), np.sin(angles)], axis=1)  # circumradius = side
    return Scenario(positions, goal, np.zeros((0, 3)))


@pytest.mark.parametrize("preset", ["ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing"])
@pytest.mark.parametrize("n_agents", [3, 4, 6])
def test_parallel_api(preset: str, n_agents: int) -> None:
    env = FormationEnv(FormationConfig.task(preset, n_agents=n_agents, stage=3, max_steps=400))
    parallel_api_test(env, num_cycles=500)


def test_agents_and_spaces() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing"))
    assert env.possible_agents == [f"agent_{i}" for i in range(6)]
    assert env.observation_space("agent_0") is env.observation_space("agent_5")
    assert env.action_space("agent_0") is env.action_space("agent_3")
    assert env.observation_space("agent_0").shape == (211,)  # 2 x 90 lidar + 31 (Table 3.1)
    assert env.action_space("agent_0").low.tolist() == [-1, -1] and env.action_space("agent_0").high.tolist() == [1, 1]


def test_observation_layout_covers_the_vector_in_order() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing"))
    layout = env.observation_layout
    assert layout["lidar_obstacles"] == slice(0, 90) and layout["lidar_agents"] == slice(90, 180)
    position = 0
    for field_slice in layout.values():
        assert field_slice.start == position
        position = field_slice.stop
    assert position == env.observation_space("agent_0").shape[0]
    flagged = np.flatnonzero(env.binary_observation_mask).tolist()
    assert flagged == [layout["flag_orientation"].start, layout["flag_range"].start]


def test_reset_observation_values_match_the_scenario() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    env = FormationEnv(config)
    scenario = hexagon_scenario((5.0, 5.0), (9.0, 8.0))
    observations, infos = env.reset(seed=0, options={"scenario": scenario})
    layout = env.observation_layout
    for index, agent in enumerate(env.agents):
        observation = observations[agent]
        position = scenario.agent_positions[index]
        np.testing.assert_allclose(observation[layout["goal_offset"]], np.array([9.0, 8.0]) - position, atol=1e-6)
        np.testing.assert_allclose(observation[layout["centroid_goal_offset"]], [4.0, 3.0], atol=1e-6)
        np.testing.assert_allclose(observation[layout["centroid_goal_offset_change"]], [0.0, 0.0])
        np.testing.assert_allclose(observation[layout["neighbour_distances"]], [1.0, 1.0], atol=1e-6)  # hexagon side
        np.testing.assert_allclose(observation[layout["neighbour_distance_errors"]], [-0.5, -0.5], atol=1e-6)  # 1 - 1.5
        np.testing.assert_allclose(observation[layout["centroid_distance"]], [1.0], atol=1e-6)
        np.testing.assert_allclose(observation[layout["centroid_distance_error"]], [0.2], atol=1e-6)  # 1.2 - 1
        np.testing.assert_allclose(observation[layout["angle_error"]], [0.0], atol=1e-4)
        assert observation[layout["flag_orientation"]].tolist() == [1.0]
        assert observation[layout["flag_range"]].tolist() == [1.0]
        assert observation[layout["time_step"]].tolist() == [0.0]
        assert observation[layout["velocity"]].tolist() == [0.0, 0.0]
        assert observation[layout["previous_action"]].tolist() == [0.0, 0.0]
        info = infos[agent]
        assert list(info) == list(INFO_KEYS) and len(INFO_KEYS) == 9 + len(REWARD_TERMS)
        assert info["goal_distance"] == pytest.approx(5.0)  # 3-4-5 triangle
        assert info["angle_error_deg"] == pytest.approx(0.0, abs=1e-9)
        assert info["bearing_error"] == pytest.approx(0.0, abs=1e-9)
        assert all(isinstance(value, (bool, int, float)) for value in info.values())  # flat: any client stacks them


def test_neighbours_hidden_and_non_neighbours_seen_on_the_agent_channel() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing", stage=3))
    observations, _ = env.reset(options={"scenario": hexagon_scenario((5.0, 5.0), (12.0, 5.0))})
    lidar_agents = observations["agent_0"][env.observation_layout["lidar_agents"]]
    # Agent 0 sits at (5, 4). Its neighbours 1 and 5 are 1 m away (they would read (1 - 0.4) / 1.5 = 0.4): hidden.
    # Agents 2 and 4 are sqrt(3) m away at 60 and 120 deg, exactly on rays 15 and 30: (sqrt(3) - 0.4) / 1.5.
    # Agent 3 is 2 m away straight up: its surface gap 1.6 m exceeds the 1.5 m range, so it is not seen.
    expected = (math.sqrt(3) - 0.4) / 1.5
    assert lidar_agents[15] == pytest.approx(expected, abs=1e-6)
    assert lidar_agents[30] == pytest.approx(expected, abs=1e-6)
    assert lidar_agents.min() == pytest.approx(expected, abs=1e-6)
    assert lidar_agents[22] == 1.0 and lidar_agents[23] == 1.0


def test_same_seed_same_500_steps_bit_for_bit() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    first, second = FormationEnv(config), FormationEnv(config)
    obs_a, info_a = first.reset(seed=123)
    obs_b, info_b = second.reset(seed=123)
    rng_a, rng_b = np.random.default_rng(7), np.random.default_rng(7)
    assert info_a == info_b
    for _ in range(500):
        for agent in obs_a:
            assert obs_a[agent].tobytes() == obs_b[agent].tobytes()
        result_a = first.step(random_actions(first, rng_a))
        result_b = second.step(random_actions(second, rng_b))
        obs_a, obs_b = result_a[0], result_b[0]
        assert result_a[1:] == result_b[1:]  # rewards, terminations, truncations and infos compare exactly
        assert first.world.positions.tobytes() == second.world.positions.tobytes()
        assert first.world.velocities.tobytes() == second.world.velocities.tobytes()
        if not first.agents:
            obs_a, _ = first.reset()
            obs_b, _ = second.reset()


def test_different_seeds_draw_different_scenarios() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing", stage=3))
    goals = set()
    for seed in range(10):
        env.reset(seed=seed)
        goals.add(tuple(env.scenario.goal.tolist()) + tuple(env.scenario.obstacles.ravel().tolist()))
    assert len(goals) == 10
    env.reset(seed=3)
    first = env.scenario
    env.reset(seed=3)
    assert first.goal.tolist() == env.scenario.goal.tolist()


def test_truncation_at_max_steps_with_r_late() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing", stage=3, max_steps=5))
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for step in range(1, 6):
        _, _, terminations, truncations, infos = env.step(random_actions(env, rng))
        assert not any(terminations.values())
        assert all(truncations.values()) == (step == 5)
        assert infos["agent_0"]["reward_time"] == (-10.0 if step == 5 else 0.0)
    assert env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_termination_when_the_centroid_reaches_the_goal() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    env = FormationEnv(config)
    # centroid (5, 5), goal 0.41 m to the right: one full step right moves the centroid 0.015 m -> 0.395 <= eta_g 0.4
    env.reset(options={"scenario": hexagon_scenario((5.0, 5.0), (5.41, 5.0))})
    actions = {agent: np.array([1.0, 0.0]) for agent in env.agents}
    _, _, terminations, truncations, infos = env.step(actions)
    assert all(terminations.values()) and not any(truncations.values())
    assert infos["agent_0"]["success"] is True
    assert infos["agent_0"]["goal_distance"] == pytest.approx(0.395)
    assert infos["agent_0"]["reward_goal"] == 4.0  # r_reached (Table 5.1)
    assert env.agents == []


def test_reward_is_the_clipped_weighted_sum_of_the_info_terms() -> None:
    # Table 5.1 with K_bearing = 0.3, K_angle = 0 (ch5-bearing), time and centroid terms unweighted (eq. 42)
    weights = {"time": 1, "angle": 0, "bearing": 0.3, "dist": 1, "centroid": 1, "goal": 0.5, "move": 0.3, "velocity": 0.1}
    weights["coll"] = 0.5
    disabled = {1: {"dist", "angle", "bearing"}, 2: {"angle", "bearing"}, 3: set()}
    for stage in (1, 2, 3):
        env = FormationEnv(FormationConfig.task("ch5-bearing", stage=stage))
        env.reset(seed=stage)
        rng = np.random.default_rng(stage)
        for _ in range(30):
            _, rewards, _, _, infos = env.step(random_actions(env, rng))
            for agent, reward in rewards.items():
                terms = {name: infos[agent][f"reward_{name}"] for name in REWARD_TERMS}
                expected = sum(weights[name] * value for name, value in terms.items() if name not in disabled[stage])
                assert reward == pytest.approx(min(max(expected, -10.0), 10.0), abs=1e-9)


def test_set_stage_switches_reward_gating_and_placement() -> None:
    env = FormationEnv(FormationConfig.task("ch4-individual", stage=1))
    env.reset(seed=0)
    assert env.scenario.centroid[0] == pytest.approx(env.scenario.goal[0])  # stage 1: centroid x = goal x
    env.set_stage(3)
    env.reset(seed=0)
    assert env.scenario.centroid[0] != pytest.approx(env.scenario.goal[0])
    assert len(env.scenario.obstacles) == 3  # ch4 stage 3: one 80 cm and two 50 cm obstacles
    with pytest.raises(ValueError, match="stage"):
        env.set_stage(4)


def test_actions_are_validated_and_clipped() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    env = FormationEnv(config)
    env.reset(seed=0)
    good = {agent: np.zeros(2) for agent in env.agents}
    with pytest.raises(ValueError, match="agent_2"):
        env.step({**good, "agent_2": np.array([np.nan, 0.0])})
    with pytest.raises(ValueError, match="agent_4"):
        env.step({**good, "agent_4": np.array([np.inf, 0.0])})
    with pytest.raises(ValueError, match=r"agent_1.*shape"):
        env.step({**good, "agent_1": np.zeros(3)})
    missing = dict(good)
    del missing["agent_5"]
    with pytest.raises(ValueError, match="agent_5"):
        env.step(missing)
    with pytest.raises(ValueError, match="agent_9"):
        env.step({**good, "agent_9": np.zeros(2)})
    # an action of 7 acts as 1: two envs from the same state end in the same place
    twin = FormationEnv(config)
    twin.reset(seed=0)
    env.step({agent: np.array([7.0, -3.0]) for agent in env.agents})
    twin.step({agent: np.array([1.0, -1.0]) for agent in twin.agents})
    assert env.world.positions.tobytes() == twin.world.positions.tobytes()


def test_reset_rejects_bad_scenarios() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing"))
    with pytest.raises(ValueError, match="agent_0 and agent_1 overlap"):
        env.reset(options={"scenario": Scenario([[5, 5], [5.1, 5], [7, 5], [8, 5], [9, 5], [10, 5]], [12, 5])})
    with pytest.raises(TypeError, match="Scenario"):
        env.reset(options={"scenario": [[5, 5]]})
    env.reset(options={"something_else": 1})  # unknown option keys are ignored, as in Gymnasium


def test_agent_contacts_are_counted_per_pair_and_penalised() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    env = FormationEnv(config)
    positions = [[5.0, 5.0], [5.41, 5.0], [8.0, 8.0], [9.0, 8.0], [10.0, 8.0], [11.0, 8.0]]
    env.reset(options={"scenario": Scenario(positions, [2.0, 2.0])})
    actions = {agent: np.zeros(2) for agent in env.agents}
    actions["agent_0"], actions["agent_1"] = np.array([1.0, 0.0]), np.array([-1.0, 0.0])
    for _ in range(5):
        _, _, _, _, infos = env.step(actions)
    assert [infos[agent]["collisions_agent"] for agent in env.agents] == [1, 1, 0, 0, 0, 0]
    assert infos["agent_0"]["reward_coll"] == -1.0  # r_j
    assert infos["agent_2"]["reward_coll"] == 0.0


def test_rgb_array_render() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing", stage=1), render_mode="rgb_array", render_lidar=True)
    with pytest.raises(RuntimeError, match="reset"):
        env.render()
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (600, 900, 3) and frame.dtype == np.uint8  # 15 m x 10 m at 60 px/m
    assert frame.reshape(-1, 3).std(axis=0).min() > 5  # not blank
    # agent 0 is drawn in its own colour (tab10 blue) at its position (y up)
    x, y = env.world.positions[0] * 60
    assert tuple(frame[int(600 - y), int(x)]) == (31, 119, 180)


def test_render_mode_is_validated() -> None:
    with pytest.raises(ValueError, match="render_mode"):
        FormationEnv(render_mode="video")


def test_render_takes_the_mode_as_older_wrappers_pass_it() -> None:
    """RLlib's ``ParallelPettingZooEnv.render()`` calls ``par_env.render(self.render_mode)``."""
    env = FormationEnv(FormationConfig.task("ch4-individual"), render_mode="rgb_array")
    env.reset(seed=3)
    assert np.array_equal(env.render("rgb_array"), env.render())
    unset = FormationEnv(FormationConfig.task("ch4-individual"))
    unset.reset(seed=3)
    assert np.array_equal(unset.render("rgb_array"), env.render())
    with pytest.raises(ValueError, match="render mode 'video' is not supported"):
        env.render("video")


def test_every_observation_field_matches_the_state_after_steps() -> None:
    """Each field, read by name, recomputed from positions and velocities with plain numpy."""
    config = FormationConfig.task("ch5-angle", stage=3)
    env = FormationEnv(config)
    # an irregular hexagon with one side longer than d_ref = 1.5 m, so that flag_range is 0 and errors differ by agent
    positions = [[5.0, 4.0], [6.0, 4.3], [6.4, 5.4], [5.2, 6.0], [4.1, 5.6], [3.9, 4.2]]  # side 3-4: 1.17, 4-5: 1.41
    positions[4] = [3.6, 5.9]  # side 3-4 now 1.70 m
    env.reset(options={"scenario": Scenario(positions, [12.0, 8.0])})
    rng = np.random.default_rng(11)
    for _ in range(20):
        previous_offset = env.goal - env.world.positions.mean(axis=0)
        actions = random_actions(env, rng)
        observations, rewards, _, _, _ = env.step(actions)
    positions, velocities, goal = env.world.positions, env.world.velocities, env.goal
    centroid = positions.mean(axis=0)
    layout = env.observation_layout
    angle_errors, sides = [], []
    for index in range(6):
        to_previous = positions[(index - 1) % 6] - positions[index]
        to_following = positions[(index + 1) % 6] - positions[index]
        beta = np.degrees(np.arctan2(to_previous[1], to_previous[0]) - np.arctan2(to_following[1], to_following[0])) % 360
        angle_errors.append(120.0 - beta)
        sides.append(np.hypot(*to_following))
    range_ok = max(sides) <= 1.5
    for index, agent in enumerate(env.agents):
        previous, following = (index - 1) % 6, (index + 1) % 6
        to_previous, to_following = positions[previous] - positions[index], positions[following] - positions[index]
        distances = [np.hypot(*to_previous), np.hypot(*to_following)]
        angles = np.degrees(np.arctan2(to_previous[1], to_previous[0]) - np.arctan2(to_following[1], to_following[0])) % 360
        expected = {
            "velocity": velocities[index],
            "neighbour_offsets": np.r_[to_previous, to_following],
            "neighbour_relative_velocities": np.r_[
                velocities[previous] - velocities[index], velocities[following] - velocities[index]
            ],
            "goal_offset": goal - positions[index],
            "centroid_goal_offset": goal - centroid,
            "centroid_goal_offset_change": (goal - centroid) - previous_offset,
            "neighbour_distances": distances,
            "centroid_distance": [np.hypot(*(positions[index] - centroid))],
            "neighbour_distance_errors": np.array(distances) - 1.5,
            "centroid_distance_error": [1.2 - np.hypot(*(positions[index] - centroid))],
            "angle_error": [120.0 - angles],
            "neighbour_angle_errors": [angle_errors[previous], angle_errors[following]],
            "flag_range": [float(range_ok)],
            "flag_orientation": [float(0 < angles < 180)],
            "time_step": [20.0],
            "previous_action": np.clip(actions[agent], -1, 1),
            "previous_reward": [rewards[agent]],
        }
        for name, value in expected.items():
            np.testing.assert_allclose(observations[agent][layout[name]], value, rtol=1e-5, atol=1e-5, err_msg=name)


def test_docstring_observation_table_matches_the_layout() -> None:
    """The thesis-style table in the class docstring lists every field with its true index range."""
    env = FormationEnv(FormationConfig.task("ch5-bearing"))
    rows = {}
    for line in FormationEnv.__doc__.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[1] in env.observation_layout:
            first, _, last = cells[0].partition("-")
            rows[cells[1]] = slice(int(first), int(last or first) + 1)
    assert rows == env.observation_layout


def test_wall_contact_is_counted_and_penalised() -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    env = FormationEnv(config)
    positions = [[0.25, 5.0], [3.0, 3.0], [4.0, 3.0], [5.0, 3.0], [6.0, 3.0], [7.0, 3.0]]
    env.reset(options={"scenario": Scenario(positions, [12.0, 8.0])})
    actions = {agent: np.zeros(2) for agent in env.agents}
    actions["agent_0"] = np.array([-1.0, 0.0])
    _, _, _, _, infos = env.step(actions)  # 0.05 m gap, 0.015 m per step: in contact after 4 steps
    assert infos["agent_0"]["reward_coll"] == -5.0  # r_o: the gap 0.05 - 0.015 = 0.035 m < d_safe 0.05 m
    for _ in range(4):
        _, _, _, _, infos = env.step(actions)
    assert [infos[agent]["collisions_obstacle"] for agent in env.agents] == [1, 0, 0, 0, 0, 0]
    assert infos["agent_1"]["reward_coll"] == 0.0


def test_non_numeric_action_names_the_agent() -> None:
    env = FormationEnv(FormationConfig.task("ch5-bearing"))
    env.reset(seed=0)
    actions = {agent: np.zeros(2) for agent in env.agents}
    actions["agent_3"] = ["a", 1]
    with pytest.raises(ValueError, match="action of agent_3 is not real numbers"):
        env.step(actions)


def test_reference_bearings_are_observed_last_only_when_asked() -> None:
    plain = FormationEnv(FormationConfig.task("ch5-bearing", n_agents=4))
    env = FormationEnv(FormationConfig.task("ch5-bearing", n_agents=4, observe_reference_bearings=True))
    assert "reference_bearings" not in plain.observation_layout and env.observation_layout["reference_bearings"] == slice(
        211, 215
    )
    assert not env.binary_observation_mask[211:].any()
    observations, _ = env.reset(seed=3)
    plain_observations, _ = plain.reset(seed=3)
    # a square traversed anti-clockwise: the edge from agent i to i + 1 points at 45 + 90 i deg (Table 5.2's rule)
    r = np.sqrt(0.5)
    expected = {0: [-r, r, r, r], 1: [-r, -r, -r, r], 2: [r, -r, -r, -r], 3: [r, r, r, -r]}
    for _ in range(3):
        for agent, bearings in expected.items():
            row = observations[f"agent_{agent}"]
            np.testing.assert_allclose(row[211:], bearings, atol=1e-7)
            assert row[:211].tobytes() == plain_observations[f"agent_{agent}"].tobytes()  # Table 3.1's part unchanged
            assert env.observation_space(f"agent_{agent}").contains(row)
        actions = {agent: np.array([0.3, -0.2]) for agent in env.agents}
        observations, *_ = env.step(actions)
        plain_observations, *_ = plain.step(actions)


def test_actions_that_are_not_real_numbers_or_not_a_dict_are_one_line_errors() -> None:
    env = FormationEnv()
    env.reset(seed=0)
    complex_action = {agent: np.array([0.5 + 1j, 0.0]) for agent in env.agents}  # numpy would keep 0.5 with a warning
    with pytest.raises(ValueError, match=r"action of agent_0 is not real numbers: array\(\[0\.5\+1\.j, 0\. \+0\.j\]\)"):
        env.step(complex_action)
    with pytest.raises(ValueError, match="actions must be real numbers, got complex128 values"):
        env.step_array(np.full((6, 2), 0.5 + 1j))
    with pytest.raises(TypeError, match=r"step\(\) takes a dict of one action per agent .* got list; step_array\(\)"):
        env.step([[0.1, 0.1]] * 6)
    assert env.team_state().step == 0  # nothing stepped
