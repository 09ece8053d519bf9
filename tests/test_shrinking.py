"""The shrinking controller: its parts against hand-computed cases, its decentralisation, and a placed passage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_formation.controllers import CONTROLLERS, ShrinkingController, ShrinkingGains
from sb3_formation.controllers.base import ring_shape
from sb3_formation.controllers.classical import force_action, lidar_repulsion
from sb3_formation.controllers.shrinking import MEMORY_FIELDS, close_neighbour_repulsion, rotate
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.geometry import reference_polygon
from sb3_formation.env.scenarios import Scenario, start_formation
from sb3_formation.env.sensors import ray_directions

CH5 = FormationConfig.task("ch5-bearing", stage=3)  # n = 6, R_a 0.2 m, r_0 = 1.08 m = L, v_max 0.05 m/s, dt 0.3 s
FIELD = {name: index for index, name in enumerate(MEMORY_FIELDS)}
STEP = CH5.v_max * CH5.dt  # V dt with the default k_goal = 1


def memory(controller: ShrinkingController, rows: int = 1, **values: float) -> np.ndarray:
    """A started memory of ``rows`` agents, with ``values`` by field name."""
    state = controller.initial_memory(rows)
    state[:, FIELD["started"]] = 1.0
    for name, value in values.items():
        state[:, FIELD[name]] = value
    return state


def test_registered_and_gains_checked_and_recorded() -> None:
    assert CONTROLLERS["shrinking"] is ShrinkingController
    controller = ShrinkingController(CH5, patience=10)
    assert controller.gains["patience"] == 10 and controller.gains["k_goal"] == ShrinkingGains().k_goal
    assert not getattr(controller, "privileged", False)
    with pytest.raises(ValueError, match="k_obstacle=-1"):
        ShrinkingController(CH5, k_obstacle=-1)
    with pytest.raises(ValueError, match="unknown gains"):
        ShrinkingController(CH5, speed=1.0)
    with pytest.raises(ValueError, match="gap_high"):
        ShrinkingGains(gap_low=1.0, gap_high=0.5)


def test_scale_agreement_by_hand() -> None:
    """s_i = clip(min(s_lidar, min_j |d_j| / L + delta, s_prev + rho), s_min, 1)."""
    controller, ring = ShrinkingController(CH5), ring_shape(CH5, 6)
    gains, side = controller.settings, CH5.start_side_length
    free = np.ones((1, CH5.lidar_rays))
    assert controller.min_scale(ring) == pytest.approx((0.4 + gains.min_side_gap) / side)
    # nothing seen, neighbours at the starting side: full scale
    offsets = np.array([[[side, 0.0], [0.0, side]]])
    assert controller.agreed_scale(free, offsets, np.array([1.0]), ring)[0] == 1.0
    # a neighbour at 0.6 L: the agent follows it down to 0.6 + delta
    shrunk = np.array([[[0.6 * side, 0.0], [0.0, side]]])
    assert controller.agreed_scale(free, shrunk, np.array([1.0]), ring)[0] == pytest.approx(0.6 + gains.scale_slack)
    # growing back by at most rho per step
    assert controller.agreed_scale(free, offsets, np.array([0.5]), ring)[0] == pytest.approx(0.5 + gains.scale_relax)
    # never below s_min
    touching = np.array([[[0.3, 0.0], [0.0, side]]])
    assert controller.agreed_scale(free, touching, np.array([1.0]), ring)[0] == pytest.approx(controller.min_scale(ring))


def test_lidar_scale_by_hand() -> None:
    """Proximity: a wall 0.5 m away (half-way between g_lo 0.2 and g_hi 0.8) gives s_min + (1 - s_min) / 2. Width:
    walls 0.6 m to either side (rays 0 and 45, opposite) give w = 1.6 m and s_w = (0.8 - 0.2 - m_w) / r_0."""
    controller, ring = ShrinkingController(CH5), ring_shape(CH5, 6)
    gains, s_min, l_s = controller.settings, controller.min_scale(ring), CH5.lidar_range
    one_side = np.ones((1, CH5.lidar_rays))
    one_side[0, 10] = 0.5 / l_s
    assert controller.lidar_scale(one_side, ring)[0] == pytest.approx(s_min + (1 - s_min) * 0.5)
    both = np.ones((1, CH5.lidar_rays))
    both[0, 0] = both[0, 45] = 0.6 / l_s
    width_scale = (1.6 / 2 - 0.2 - gains.width_margin) / CH5.start_circumradius
    proximity = s_min + (1 - s_min) * (0.6 - gains.gap_low) / (gains.gap_high - gains.gap_low)
    assert controller.lidar_scale(both, ring)[0] == pytest.approx(min(width_scale, proximity))


def test_team_heading_free_blocked_flip_and_leave() -> None:
    controller = ShrinkingController(CH5, patience=0, wall_search=False, k_goal=1.0)  # the radial-flip detour
    gains = controller.settings
    goal = np.array([[5.0, 0.0]])
    # free: a full step along the last heading keeps the heading on the goal
    state = memory(controller, heading_x=1.0)
    heading = controller.team_heading(goal, np.array([[-STEP, 0.0]]), state)
    np.testing.assert_allclose(heading, [[1.0, 0.0]])
    assert state[0, FIELD["phi"]] == 0 and state[0, FIELD["progress"]] == pytest.approx(1.0)
    # blocked, drifting to the left of the goal direction: the detour starts on the left (sigma = +1)
    state = memory(controller, heading_x=1.0, progress=0.2, lateral=0.3)
    heading = controller.team_heading(goal, np.array([[0.0, -0.1 * STEP]]), state)
    turn = math.radians(gains.turn_block_deg)
    np.testing.assert_allclose(heading, [[math.cos(turn), math.sin(turn)]])
    assert state[0, FIELD["sigma"]] == 1 and state[0, FIELD["hit"]] == pytest.approx(5.0)
    # drifting right: the right side
    state = memory(controller, heading_x=1.0, progress=0.2, lateral=-0.3)
    controller.team_heading(goal, np.zeros((1, 2)), state)
    assert state[0, FIELD["sigma"]] == -1
    # a detour that took the centroid D_flip further than its anchor turns back by pi on the other side
    far = np.array([[5.0 + gains.flip_distance + 0.5, 0.0]])
    state = memory(controller, heading_x=1.0, phi=math.radians(100), sigma=1, anchor=5.0, hit=5.0)
    controller.team_heading(far, np.array([[-STEP, 0.0]]), state)
    free_turn = math.radians(gains.turn_back_deg)
    assert state[0, FIELD["sigma"]] == -1 and state[0, FIELD["flips"]] == 1
    assert state[0, FIELD["phi"]] == pytest.approx(math.pi - (math.radians(100) - free_turn))
    assert state[0, FIELD["anchor"]] == pytest.approx(far[0, 0])
    # the next flip needs twice the distance
    state[0, FIELD["phi"]] = math.radians(100)
    farther = far + np.array([[gains.flip_distance + 0.5, 0.0]])
    controller.team_heading(farther, np.array([[-STEP, 0.0]]), state)
    assert state[0, FIELD["flips"]] == 1
    # heading on the goal again and closer than the closest blocked point by the margin: the detour ends
    near = np.array([[5.0 - gains.leave_margin - 0.1, 0.0]])
    state = memory(controller, heading_x=1.0, sigma=1, anchor=5.0, hit=5.0, flips=1)
    controller.team_heading(near, np.array([[-STEP, 0.0]]), state)
    assert state[0, FIELD["hit"]] == 0


def test_patience_waits_before_turning() -> None:
    controller = ShrinkingController(CH5, patience=3, wall_search=False)  # a 1 deg turn after patience
    state = memory(controller, heading_x=1.0, progress=0.0)
    for _ in range(3):
        controller.team_heading(np.array([[5.0, 0.0]]), np.zeros((1, 2)), state)
        assert state[0, FIELD["phi"]] == 0
    controller.team_heading(np.array([[5.0, 0.0]]), np.zeros((1, 2)), state)
    assert state[0, FIELD["phi"]] == pytest.approx(math.radians(controller.settings.turn_block_deg))


def test_first_action_is_the_force_conversion_of_the_command() -> None:
    """No obstacle in range, at the start, the team at 0.9 r_0: v_i = V c_g / |c_g| + k_place (s r_0 u_i - o_i) with
    s = 0.9 + delta, plus the repulsion of the agents the agent lidar sees, through force_action."""
    env = FormationEnv(CH5)
    start = reference_polygon(6, CH5.start_circumradius) * 0.9 + np.array([3.0, 5.0])
    observations, _ = env.reset(options={"scenario": Scenario(start, goal=[12.0, 5.0])})
    rows = np.stack(list(observations.values())).astype(np.float64)
    controller = ShrinkingController(CH5)
    actions, state = controller.predict(rows)
    layout, gains = controller.layout, controller.settings
    goal = rows[:, layout["centroid_goal_offset"]]
    own = goal - rows[:, layout["goal_offset"]]
    scale = 0.9 + gains.scale_slack  # the neighbours' distances show 0.9 L
    places = scale * CH5.start_circumradius * reference_polygon(6, 1.0)
    command = gains.k_goal * CH5.v_max * goal / np.linalg.norm(goal, axis=1, keepdims=True)
    command += gains.k_place * (places - own)
    command += gains.k_agent * lidar_repulsion(rows[:, layout["lidar_agents"]], CH5, ray_directions(CH5.lidar_rays))
    expected = force_action(command, rows[:, layout["velocity"]], CH5)
    np.testing.assert_allclose(actions, expected.astype(np.float32), rtol=1e-5, atol=1e-6)
    assert state.shape == (6, len(MEMORY_FIELDS))


def test_close_neighbour_repulsion_and_rotation() -> None:
    offsets = np.array([[[0.5, 0.0], [0.0, 1.0]]])  # gaps 0.1 m (within 0.15) and 0.6 m
    np.testing.assert_allclose(close_neighbour_repulsion(offsets, 0.2, 0.15), [[-(1 / 0.1 - 1 / 0.15), 0.0]])
    np.testing.assert_allclose(rotate(np.array([[1.0, 0.0]]), np.array([math.pi / 2])), [[0.0, 1.0]], atol=1e-12)


def test_acts_from_its_observation_and_memory_alone() -> None:
    """Actions depend on each row, its agent index and the agents' own memory: a copy of the world gives the same
    actions, a fresh controller given the same rows and memory acts the same, and the shared part of the memory is
    the same for every agent of a team."""
    config = CH5.replace(scenes="passage")

    def play(steps: int) -> tuple[np.ndarray, np.ndarray]:
        env = FormationEnv(config)
        rows = np.stack(list(env.reset(seed=5)[0].values()))
        controller, state = ShrinkingController(config), None
        for _ in range(steps):
            actions, state = controller.predict(rows, state)
            rows, *_ = env.step_array(actions)
        return rows, state

    rows, state = play(400)
    twin_rows, twin_state = play(400)
    np.testing.assert_array_equal(rows, twin_rows)
    np.testing.assert_array_equal(state, twin_state)
    actions, next_state = ShrinkingController(config).predict(rows, state.copy())
    fresh, fresh_state = ShrinkingController(config).predict(rows, state.copy(), np.zeros(6, dtype=bool))
    np.testing.assert_array_equal(actions, fresh)
    np.testing.assert_array_equal(next_state, fresh_state)
    shared = [FIELD[name] for name in ("phi", "sigma", "anchor", "hit", "flips", "heading_x", "heading_y")]
    assert np.all(next_state[:, shared] == next_state[0, shared])
    # two teams in one batch: the second acts as it does alone; an episode start resets only its rows
    batch, batch_state = ShrinkingController(config).predict(
        np.concatenate([rows, rows]), np.concatenate([state, state]), np.repeat([True, False], 6)
    )
    np.testing.assert_array_equal(batch[6:], actions)
    np.testing.assert_array_equal(batch_state[:6, FIELD["phi"]], 0.0)


def test_passes_a_placed_passage_off_the_straight_line() -> None:
    """A wall across x = 7.5 with a 1.6 m opening (narrower than the 2.56 m starting formation) centred on y = 6.5,
    the team at (3, 5) and the goal at (12, 5): it shrinks, slides to the opening and reaches the goal."""
    half = 0.8 + 0.1
    walls = [[7.5, 0.0, 7.5, 6.5 - half, 0.2], [7.5, 6.5 + half, 7.5, 10.0, 0.2]]
    env = FormationEnv(CH5)
    observations, _ = env.reset(
        options={"scenario": Scenario(start_formation(CH5, np.array([3.0, 5.0])), [12.0, 5.0], walls=walls)}
    )
    rows, controller, state = np.stack(list(observations.values())), ShrinkingController(CH5), None
    smallest = np.inf
    for _ in range(CH5.max_steps):
        actions, state = controller.predict(rows, state)
        rows, _, terminated, truncated, _ = env.step_array(actions)
        smallest = min(smallest, state[:, FIELD["scale"]].max())
        if terminated or truncated:
            break
    assert terminated
    assert smallest < 0.8  # the whole team shrank to pass
