"""The classical controller: its parts against hand-computed cases, its decentralisation, and whole episodes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_formation.controllers import CONTROLLERS, ClassicalController
from sb3_formation.controllers.classical import apex_offset, force_action, lidar_repulsion, neighbour_repulsion
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.geometry import reference_bearings, reference_polygon
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.sensors import ray_directions
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.targets import load_policy

CH5 = FormationConfig.task("ch5-bearing", stage=3)


def test_repulsion_from_one_lidar_reading() -> None:
    readings = np.ones((1, CH5.lidar_rays))
    readings[0, 0] = 0.2  # ray 0 points along +x; the gap is 0.2 * 1.5 m = 0.3 m
    push = lidar_repulsion(readings, CH5, ray_directions(CH5.lidar_rays))
    expected = (1 / 0.3 - 1 / 1.5) * 2 * math.pi / 90  # 2.6667 per metre times 4 deg of rays
    np.testing.assert_allclose(push, [[-expected, 0.0]], atol=1e-12)
    # within a shorter reach the same reading pushes (1/0.3 - 1/0.5); beyond it, not at all
    short = lidar_repulsion(readings, CH5, ray_directions(CH5.lidar_rays), reach=0.5)
    np.testing.assert_allclose(short, [[-(1 / 0.3 - 2.0) * 2 * math.pi / 90, 0.0]], atol=1e-12)
    assert not lidar_repulsion(readings, CH5, ray_directions(CH5.lidar_rays), reach=0.25).any()
    # a ray at 90 deg (ray 22.5 does not exist: use ray 45, pointing along -x) pushes along +x
    readings[0, 0], readings[0, 45] = 1.0, 0.5
    np.testing.assert_allclose(
        lidar_repulsion(readings, CH5, ray_directions(CH5.lidar_rays)),
        [[(1 / 0.75 - 1 / 1.5) * 2 * math.pi / 90, 0.0]],
        atol=1e-12,
    )


def test_neighbour_repulsion_pushes_only_within_range() -> None:
    # neighbour 0.9 m away along +y: surface gap 0.9 - 0.4 = 0.5 m; the other 2.5 m away: gap 2.1 m > 1.5 m
    offsets = np.array([[[0.0, 0.9], [2.5, 0.0]]])
    np.testing.assert_allclose(neighbour_repulsion(offsets, CH5), [[0.0, -(1 / 0.5 - 1 / 1.5)]], atol=1e-12)


def test_bearing_consensus_of_a_known_layout() -> None:
    controller = ClassicalController(CH5)
    side = CH5.start_side_length
    reference = reference_bearings(6)
    offsets = side * reference[[2]]  # agent 2 exactly where its neighbours want it
    np.testing.assert_allclose(controller.formation_velocity(offsets, np.array([2])), [[0.0, 0.0]], atol=1e-15)
    # the preceding neighbour 0.4 m further along +x: it alone implies a position 0.4 m along +x, so the mean is 0.2 m
    moved = offsets.copy()
    moved[0, 0, 0] += 0.4
    k = controller.settings.k_formation
    np.testing.assert_allclose(controller.formation_velocity(moved, np.array([2])), [[0.2 * k, 0.0]], atol=1e-15)


def test_angle_consensus_is_the_apex_of_the_reference_angle() -> None:
    # neighbours at (-1, 1) (preceding) and (1, 1) (succeeding), beta_ref 90 deg: the apex is the agent's own place
    np.testing.assert_allclose(apex_offset(np.array([[[-1.0, 1.0], [1.0, 1.0]]]), 90.0), [[0.0, 0.0]], atol=1e-15)
    np.testing.assert_allclose(apex_offset(np.array([[[-1.0, 2.0], [1.0, 2.0]]]), 90.0), [[0.0, 1.0]], atol=1e-15)
    # beta_ref 60 deg over a base of 2 m: height 1 / tan(30 deg) = sqrt(3) below the midpoint
    np.testing.assert_allclose(apex_offset(np.array([[[-1.0, 0.0], [1.0, 0.0]]]), 60.0), [[0.0, -math.sqrt(3)]], atol=1e-12)
    # every vertex of the reference polygon is the apex on its neighbours (anti-clockwise order, n = 5)
    polygon = reference_polygon(5, 1.3)
    offsets = np.stack([polygon[(np.arange(5) + shift) % 5] - polygon for shift in (-1, 1)], axis=1)
    np.testing.assert_allclose(apex_offset(offsets, 108.0), np.zeros((5, 2)), atol=1e-12)


def test_angle_tasks_use_no_reference_bearings() -> None:
    angle = ClassicalController(FormationConfig.task("ch5-angle"))
    assert not angle.bearings and ClassicalController(CH5).bearings
    # a whole reference polygon turned by 40 deg is in formation for the angle law, but not for the bearing law
    turn = math.radians(40)
    rotation = np.array([[math.cos(turn), math.sin(turn)], [-math.sin(turn), math.cos(turn)]])
    polygon = reference_polygon(6, CH5.start_circumradius) @ rotation
    offsets = np.stack([polygon[(np.arange(6) + shift) % 6] - polygon for shift in (-1, 1)], axis=1)
    np.testing.assert_allclose(angle.formation_velocity(offsets, np.arange(6)), np.zeros((6, 2)), atol=1e-12)
    assert np.abs(ClassicalController(CH5).formation_velocity(offsets, np.arange(6))).max() > 0.01


def test_force_conversion_and_its_clipping() -> None:
    # F_max = m v_max / dt: the action is (v* - v) / v_max, the command's speed clipped to v_max first
    np.testing.assert_allclose(force_action(np.array([[0.1, 0.0]]), np.zeros((1, 2)), CH5), [[1.0, 0.0]])
    np.testing.assert_allclose(force_action(np.array([[0.01, 0.02]]), np.array([[0.0, 0.01]]), CH5), [[0.2, 0.2]])
    # (0.03, 0.04) from (-0.05, 0): (1.6, 0.8) scaled down to fit the box, keeping its direction
    np.testing.assert_allclose(force_action(np.array([[0.03, 0.04]]), np.array([[-0.05, 0.0]]), CH5), [[1.0, 0.5]])
    heavy = CH5.replace(agent_mass=2.0, max_force=1.0)  # F_max 1 N: action = 2 kg * 0.02 m/s / 0.3 s / 1 N
    np.testing.assert_allclose(force_action(np.array([[0.02, 0.0]]), np.zeros((1, 2)), heavy), [[2 * 0.02 / 0.3, 0.0]])


def test_gains_are_checked_and_recorded() -> None:
    controller = CONTROLLERS["classical"](CH5, k_goal=0.5)
    assert controller.gains["k_goal"] == 0.5 and controller.gains["k_formation"] == 0.3
    with pytest.raises(ValueError, match="unknown gains \\['k_gaol'\\]"):
        ClassicalController(CH5, k_gaol=1.0)
    with pytest.raises(ValueError, match="k_obstacle=-1"):
        ClassicalController(CH5, k_obstacle=-1)


def test_reaches_the_goal_past_a_placed_obstacle() -> None:
    env = FormationEnv(CH5)
    start = reference_polygon(6, CH5.start_circumradius) + np.array([3.0, 5.0])
    scenario = Scenario(start, goal=[12.0, 5.0], obstacles=[[7.5, 5.0, 0.8]])  # straight across the direct path
    observations, _ = env.reset(options={"scenario": scenario})
    controller, rows = ClassicalController(CH5), np.stack(list(observations.values()))
    contacts = 0
    for _ in range(CH5.max_steps):
        actions, _ = controller.predict(rows)
        rows, _, terminated, truncated, infos = env.step_array(actions)
        contacts += sum(info["collisions_obstacle"] for info in infos)
        if terminated or truncated:
            break
    assert terminated and contacts == 0


def test_acts_from_the_observation_alone() -> None:
    """Each row's action depends on that row and its agent index only: a copy of the world, a shuffled batch or
    rows on their own give the same actions as the team played in the env."""
    env = FormationEnv(CH5)
    observations, _ = env.reset(seed=3)
    controller = ClassicalController(CH5)
    rows = np.stack(list(observations.values()))
    for _ in range(30):
        rows, *_ = env.step_array(controller.predict(rows)[0])
    actions = controller.predict(rows)[0]
    twin = FormationEnv(CH5)
    twin.reset(seed=3)
    twin_rows = np.stack(list(twin.reset(seed=3)[0].values()))
    for _ in range(30):
        twin_rows, *_ = twin.step_array(controller.predict(twin_rows)[0])
    np.testing.assert_array_equal(controller.predict(twin_rows)[0], actions)
    order = np.array([4, 0, 5, 2, 1, 3])
    alone = np.clip(controller.act(rows[order].astype(np.float64), order, deterministic=True), -1, 1)
    np.testing.assert_array_equal(alone.astype(np.float32), actions[order])
    # two teams in one batch: the second team's rows act as they do alone
    batch = controller.predict(np.concatenate([twin_rows, rows]))[0]
    np.testing.assert_array_equal(batch[6:], actions)


def test_evaluate_matches_playing_by_hand() -> None:
    config = CH5.replace(max_steps=300)
    policy = load_policy("controller:classical", recipe="ch5-bearing")
    result = evaluate(policy, 3, stage=3, seed=7, n_envs=2, env_overrides={"max_steps": 300}, record=0)
    for row in result.episodes:
        env = FormationEnv(config)
        observations, _ = env.reset(seed=row["seed"])
        rows, length, agent_contacts = np.stack(list(observations.values())), 0, 0
        while True:
            rows, _, terminated, truncated, infos = env.step_array(ClassicalController(config).predict(rows)[0])
            length += 1
            agent_contacts += sum(info["collisions_agent"] for info in infos)
            if terminated or truncated:
                break
        assert (row["length"], row["success"], row["collisions_agent"]) == (length, terminated, agent_contacts // 2)


def test_goal_attraction_turns_aside_without_progress() -> None:
    controller = ClassicalController(CH5)
    speed = 0.9 * CH5.v_max  # k_goal v_max
    goal = np.array([[2.0, 0.0], [2.0, 0.0], [2.0, 0.0]])
    # no progress: the full 80 deg detour; full progress (k_goal v_max dt closer): straight on; half: 40 deg
    change = np.array([[0.0, 0.0], [-speed * CH5.dt, 0.0], [-speed * CH5.dt / 2, 0.0]])
    turns = np.radians([80.0, 0.0, 40.0])
    expected = speed * np.stack([np.cos(turns), np.sin(turns)], axis=1)
    np.testing.assert_allclose(controller.goal_velocity(goal, change), expected, atol=1e-15)


@pytest.mark.parametrize("preset", ["ch5-angle", "ch5-bearing"])
@pytest.mark.parametrize("n_agents", [3, 10, 16])
def test_flies_teams_of_any_size_in_formation(preset: str, n_agents: int) -> None:
    """From a regular polygon turned by 25 deg (out of the bearing reference) across an empty world to the goal, with
    every interior angle near beta^ref at the end."""
    config = FormationConfig.task(preset, n_agents=n_agents, stage=3)
    turn = math.radians(25)
    rotation = np.array([[math.cos(turn), math.sin(turn)], [-math.sin(turn), math.cos(turn)]])
    start = reference_polygon(n_agents, config.start_circumradius) @ rotation + np.array([3.0, 5.0])
    env = FormationEnv(config)
    observations, _ = env.reset(options={"scenario": Scenario(start, goal=[11.0, 6.0])})
    controller, rows = ClassicalController(config), np.stack(list(observations.values()))
    for _ in range(config.max_steps):
        rows, _, terminated, truncated, infos = env.step_array(controller.predict(rows)[0])
        if terminated or truncated:
            break
    assert terminated
    assert max(abs(info["angle_error_deg"]) for info in infos) < 5.0
    assert sum(info["collisions_agent"] for info in infos) == 0
