"""Unicycle (differential-drive) agents: kinematics against hand-solved cases, the no-sideways constraint in every
sub-step, the observation and state extensions, rendering, determinism, the PettingZoo API, and the controllers'
feedback linearisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from sb3_formation import FormationConfig, FormationEnv, Scenario
from sb3_formation.controllers import ClassicalController
from sb3_formation.env.dynamics import UnicycleModel
from sb3_formation.env.rendering import PIXELS_PER_METRE
from sb3_formation.env.scenarios import start_formation
from sb3_formation.env.world import SIDEWAYS_TOLERANCE

#: three unicycles in the chapter-5 world (v_max 0.05 m/s, dt 0.3 s, turn-rate limit 0.5 rad/s)
CONFIG = FormationConfig.task("ch5-bearing", stage=3, n_agents=3, dynamics="unicycle")


def place(
    positions: list[list[float]], headings: list[float], goal: tuple[float, float] = (12.0, 9.0), **walls: list
) -> FormationEnv:
    env = FormationEnv(CONFIG)
    env.reset(options={"scenario": Scenario(np.array(positions), goal, headings=headings, **walls)})
    return env


def drive(env: FormationEnv, actions: np.ndarray, steps: int) -> list:
    """Step with the same ``(3, 2)`` actions; the team states after every step."""
    states = []
    for _ in range(steps):
        env.step_array(actions)
        states.append(env.team_state())
    return states


def test_constant_forward_speed_and_turn_rate_trace_a_circle_of_radius_v_over_w() -> None:
    """From rest, a forward action of 1 reaches v = v_max at once (F_max = m v_max / dt), then 0 holds it; a turn
    action of 0.05 turns at w = 0.025 rad/s: each agent runs on the circle of radius v / w = 2 m that touches its
    start along its starting heading, centre p0 + R (-sin theta0, cos theta0), and its heading is the path's tangent."""
    starts, headings = [[3.0, 5.0], [12.0, 5.0], [7.5, 1.2]], [0.0, math.pi, 0.0]
    env = place(starts, headings, goal=(7.5, 8.5))
    states = drive(env, np.array([[1.0, 0.05]] * 3), 1) + drive(env, np.array([[0.0, 0.05]] * 3), 400)
    radius = CONFIG.v_max / (0.05 * CONFIG.max_turn_rate)
    assert radius == pytest.approx(2.0)
    positions = np.array([state.positions for state in states])
    for agent, (start, heading) in enumerate(zip(starts, headings)):
        centre = np.array(start) + radius * np.array([-math.sin(heading), math.cos(heading)])
        distances = np.linalg.norm(positions[:, agent] - centre, axis=1)
        np.testing.assert_allclose(distances, radius, atol=1e-9)
        swept = np.linalg.norm(positions[-1, agent] - start)
        assert swept > 3.0  # far round the circle (400 steps: 3 rad)
    last = states[-1]
    to_centre = np.stack([-np.sin(last.headings), np.cos(last.headings)], axis=1)  # the heading turned left by 90 deg
    to_agent = last.positions - (np.array(starts) + radius * np.stack([-np.sin(headings), np.cos(headings)], axis=1))
    np.testing.assert_allclose((to_agent * to_centre).sum(axis=1), -radius, atol=1e-9)  # the heading is the tangent


def test_a_pure_turn_does_not_translate() -> None:
    """Turn actions of +1, -1 and 0.5 without a forward force: positions stay where they are, bit for bit, and the
    headings turn by w per second (the first sub-step of the first step still follows the rest the agents were in)."""
    starts = [[3.0, 5.0], [7.0, 5.0], [11.0, 5.0]]
    env = place(starts, [0.0, 1.0, -2.0])
    states = drive(env, np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5]]), 30)
    for state in states:
        np.testing.assert_array_equal(state.positions, starts)
        np.testing.assert_array_equal(state.velocities, 0.0)
    turned = CONFIG.max_turn_rate * (30 * CONFIG.dt - CONFIG.dt / CONFIG.physics_substeps)
    expected = np.array([0.0, 1.0, -2.0]) + np.array([1.0, -1.0, 0.5]) * turned
    np.testing.assert_allclose(np.cos(states[-1].headings), np.cos(expected), atol=1e-12)
    np.testing.assert_allclose(np.sin(states[-1].headings), np.sin(expected), atol=1e-12)


def test_no_sideways_speed_in_any_sub_step_with_agents_pressing_on_walls_and_on_each_other() -> None:
    """Agent 0 drives at an angle into the world's left wall, agents 1 and 2 into each other and into a wall of the
    scene, at full forward force for 150 steps: after every sub-step's solve no agent keeps a sideways speed above
    SIDEWAYS_TOLERANCE v_max, the observed velocity is always along the heading, and the agent at the wall stops there
    instead of creeping along it (wheels that do not skid)."""
    wall = [[9.0, 3.0, 9.0, 7.0, 0.2]]
    headings = np.array([0.8 * math.pi, 0.25 * math.pi, -0.25 * math.pi])  # no turn actions: they stay
    env = place([[0.8, 5.0], [8.3, 4.8], [8.3, 5.3]], list(headings), walls=wall)
    world, before = env.engine.worlds[0], env.team_state().positions
    touched, slips = np.zeros(2, dtype=int), []
    for step in range(150):
        env.step_array(np.array([[1.0, 0.0]] * 3))
        assert world.sideways_speed <= SIDEWAYS_TOLERANCE * CONFIG.v_max, step
        state = env.team_state()
        moved = state.positions - before  # each step's displacement, across the (fixed) heading
        slips.append(np.abs(moved[:, 1] * np.cos(headings) - moved[:, 0] * np.sin(headings)))
        before = state.positions
        touched += [state.contacts_obstacle.sum(), state.contacts_agent.sum()]
        if step == 100:
            at_wall = state.positions[0].copy()
    assert touched.min() > 50  # they did press on the walls and on each other
    slips = np.array(slips)
    assert slips[:, 0].max() < 1e-12  # the agent at the wall never slid along it
    assert slips.max() < 2e-3  # the jammed pair: only Pymunk's overlap correction, within its 1 mm slop and a step's sink
    assert at_wall[0] == pytest.approx(CONFIG.agent_radius, abs=2e-3)  # at the wall, within Pymunk's overlap
    np.testing.assert_allclose(env.team_state().positions[0], at_wall, atol=1e-6)  # and it stays there


def test_the_heading_is_observed_and_in_the_state() -> None:
    """The observation ends with (cos, sin) of the heading (before nothing else), the velocity field is the forward
    speed along it, the start faces the goal from the centroid, and state() holds the headings inside state_space."""
    env = FormationEnv(CONFIG.replace(scenes="passage"))
    observations, _ = env.reset(seed=3)
    layout, state = env.observation_layout, env.team_state()
    assert list(layout)[-1] == "heading" and layout["heading"].stop == env.observation_space("agent_0").shape[0]
    goal_direction = state.goal - state.centroid
    np.testing.assert_allclose(state.headings, math.atan2(goal_direction[1], goal_direction[0]))
    for _ in range(20):
        observations, *_ = env.step({agent: np.array([0.6, -0.4]) for agent in env.agents})
    state = env.team_state()
    rows = np.stack([observations[agent] for agent in env.agents])
    np.testing.assert_allclose(
        rows[:, layout["heading"]], np.stack([np.cos(state.headings), np.sin(state.headings)], 1), atol=1e-7
    )
    speeds = env.engine.dynamics.forward_speeds[:, None]  # the velocity field: the forward speed along the heading
    np.testing.assert_allclose(rows[:, layout["velocity"]], speeds * rows[:, layout["heading"]], atol=1e-7)
    assert np.abs(speeds).max() > 0.01
    global_state = env.state()
    assert env.state_space.contains(global_state)
    np.testing.assert_allclose(global_state[env.state_layout["headings"]], state.headings, atol=1e-6)
    holonomic = FormationEnv(CONFIG.replace(dynamics="holonomic"))
    holonomic.reset(seed=3)
    assert "heading" not in holonomic.observation_layout and holonomic.team_state().headings is None
    assert "headings" not in holonomic.state_layout


def test_a_rendered_frame_shows_each_heading() -> None:
    """A black line runs from each agent's centre to its rim along its heading: the pixel at 0.7 R_a ahead is black,
    the one 0.7 R_a behind is the agent's colour."""
    env = place([[3.0, 5.0], [7.0, 7.0], [11.0, 5.0]], [0.0, math.pi / 2, math.pi])  # the centroid's cross on none
    env.render_mode = "rgb_array"
    frame = env.render()
    height = frame.shape[0]
    for (x, y), heading in zip(env.team_state().positions, [0.0, math.pi / 2, math.pi]):
        for sign, black in ((1, True), (-1, False)):
            point = np.array([x, y]) + sign * 0.7 * CONFIG.agent_radius * np.array([math.cos(heading), math.sin(heading)])
            pixel = frame[round(height - point[1] * PIXELS_PER_METRE), round(point[0] * PIXELS_PER_METRE)]
            assert (pixel.max() < 40) == black


def test_the_same_seed_gives_the_same_episode() -> None:
    def play(seed: int) -> np.ndarray:
        env = FormationEnv(CONFIG.replace(n_agents=6, scenes="corridor"))
        env.reset(seed=seed)
        rng = np.random.default_rng(0)
        rows = [env.step_array(rng.uniform(-1, 1, (6, 2)))[0] for _ in range(50)]
        return np.stack(rows)

    np.testing.assert_array_equal(play(7), play(7))
    assert not np.array_equal(play(7), play(8))


@pytest.mark.parametrize("task,scenes", [("ch4-team", "curriculum"), ("ch5-bearing", "trap")])
def test_the_pettingzoo_api_on_unicycle_tasks(task: str, scenes: str) -> None:
    config = FormationConfig.task(task, stage=3, dynamics="unicycle", scenes=scenes, max_steps=60)
    parallel_api_test(FormationEnv(config), num_cycles=100)


@pytest.mark.parametrize("n_agents", [3, 16])
def test_teams_of_3_to_16(n_agents: int) -> None:
    env = FormationEnv(CONFIG.replace(n_agents=n_agents, world_width=30.0, world_height=20.0))
    env.reset(seed=0)
    for _ in range(20):
        observations, *_ = env.step({agent: np.array([1.0, 0.3]) for agent in env.agents})
    assert len(observations) == n_agents and np.all(np.isfinite(env.state()))


def test_bad_dynamics_are_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"dynamics='tank' is invalid.*holonomic.*unicycle"):
        FormationConfig.task("ch5-bearing", dynamics="tank")
    with pytest.raises(ValueError, match="max_turn_rate"):
        FormationConfig.task("ch5-bearing", dynamics="unicycle", max_turn_rate=0.0)
    with pytest.raises(ValueError, match="2 headings but n_agents=3"):
        place([[3.0, 5.0], [7.0, 5.0], [11.0, 5.0]], [0.0, 1.0])


def test_feedback_linearisation_by_hand() -> None:
    """Heading +x, at rest: a command of 0.03 m/s along +x is a forward push 0.03 / 0.05 = 0.6 and no turn; a command
    of 0.01 m/s along +y turns at 0.01 / l with l = v_max / w_max = 0.1 m, 0.1 rad/s = 0.2 of the limit; a command
    of 0.08 m/s along -x is clipped to v_max backwards (push -1) without turning."""
    heading = np.array([[1.0, 0.0]] * 3)
    commands = np.array([[0.03, 0.0], [0.0, 0.01], [-0.08, 0.0]])
    actions = UnicycleModel(CONFIG).steer(commands, np.zeros((3, 2)), heading)
    np.testing.assert_allclose(actions, [[0.6, 0.0], [0.0, 0.2], [-1.0, 0.0]], atol=1e-12)
    # moving at 0.05 m/s along a heading of 90 deg, a command of 0.02 m/s along -x: slow down by 0.05, turn left
    moving = UnicycleModel(CONFIG).steer(np.array([[-0.02, 0.0]]), np.array([[0.0, 0.05]]), np.array([[0.0, 1.0]]))
    np.testing.assert_allclose(moving, [[-1.0, 0.4]], atol=1e-12)


def test_the_classical_controller_drives_unicycles_to_the_goal() -> None:
    """An easy placed scene: the team of 6 starts facing +y, the goal 6 m to its right; the classical controller's
    commands, followed by feedback linearisation, bring the centroid within eta_g of the goal."""
    config = CONFIG.replace(n_agents=6)
    env = FormationEnv(config)
    positions = start_formation(config, np.array([4.0, 5.0]))
    observations, _ = env.reset(options={"scenario": Scenario(positions, [10.0, 5.0], headings=[math.pi / 2] * 6)})
    controller, rows = ClassicalController(config), np.stack(list(observations.values()))
    for _ in range(1200):
        rows, _, terminated, truncated, _ = env.step_array(controller.predict(rows)[0])
        if terminated or truncated:
            break
    assert terminated and env.team_state().goal_distance <= config.eta_g


def test_the_batched_vec_env_steps_unicycles_as_the_single_env_does() -> None:
    """Two teams in the SB3 VecEnv, stepped by two processes, give each team the observations a FormationEnv of the
    same seed gives (a single env is a batch of one)."""
    from sb3_formation import make_formation_vec_env

    vec_env = make_formation_vec_env(
        "ch5-bearing", n_envs=2, stage=3, seed=11, n_workers=2, normalize=False, dynamics="unicycle", n_agents=3
    )
    try:
        batched = [vec_env.reset()]
        actions = np.random.default_rng(1).uniform(-1, 1, (30, 6, 2)).astype(np.float32)
        batched += [vec_env.step(action)[0] for action in actions]
    finally:
        vec_env.close()
    for team in range(2):
        env = FormationEnv(CONFIG)
        single = [np.stack(list(env.reset(seed=11 + 3 * team)[0].values()))]
        single += [env.step_array(action[3 * team : 3 * team + 3])[0] for action in actions]
        np.testing.assert_array_equal(np.stack(batched)[:, 3 * team : 3 * team + 3], np.stack(single))


def test_the_shipped_unicycle_policy_acts_only_on_unicycles() -> None:
    """pretrained:ch5-bearing-unicycle flies its own task (an episode's observations carry the heading field) and is
    refused, naming the dynamics, in the holonomic task."""
    from sb3_formation import load_pretrained
    from sb3_formation.experiment.evaluation import evaluate

    policy = load_pretrained("ch5-bearing-unicycle")
    assert policy.config.dynamics == "unicycle"
    result = evaluate(policy, episodes=1, n_envs=1, env_overrides={"max_steps": 5}, record=0)
    assert result.episodes[0]["length"] == 5
    with pytest.raises(ValueError, match=r"dynamics='holonomic' \(trained with 'unicycle'\)"):
        load_pretrained("ch5-bearing-unicycle", recipe="ch5-bearing")


def test_an_engine_of_two_team_sizes_steps_one_live_team_as_a_single_env() -> None:
    """Teams of 3 and 5 unicycles that also observe their reference bearings, in one engine; only the second is reset,
    so every step takes the path for some live teams. Its rows are what a FormationEnv of 5 gives, bit for bit, with
    the heading before the reference bearings."""
    from sb3_formation.env.engine import FormationEngine

    config = CONFIG.replace(observe_reference_bearings=True)
    engine = FormationEngine([config, config.replace(n_agents=5)])
    env = FormationEnv(config.replace(n_agents=5))
    rows = engine.reset(1, seed=4)
    np.testing.assert_array_equal(rows, np.stack(list(env.reset(seed=4)[0].values())))
    layout = env.observation_layout
    assert layout["heading"].stop == layout["reference_bearings"].start
    actions = np.random.default_rng(2).uniform(-1, 1, (40, 8, 2))
    for action in actions:
        step = engine.step(action)
        single = env.step_array(action[3:])[0]
        np.testing.assert_array_equal(step.observations[3:], single)
    assert not engine.live[0]
