"""The env's public state: every attribute from ``__init__`` on, the frozen ``TeamState`` snapshot, PettingZoo's
``state()`` / ``state_space``, and rendering as a pure function of a state."""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest
from pettingzoo.test import state_test
from pettingzoo.utils.conversions import parallel_to_aec

from sb3_formation import FormationConfig, FormationEnv, Scenario, TeamState
from sb3_formation.env.rendering import render_frame
from sb3_formation.env.scenarios import start_formation
from sb3_formation.env.scenes import scene_slots
from sb3_formation.env.state import state_layout

#: A square of four agents around (5, 5) (side 1 m), the goal 3 m to the right of the centroid, two obstacles.
SQUARE = Scenario(
    agent_positions=[[4.5, 4.5], [5.5, 4.5], [5.5, 5.5], [4.5, 5.5]],
    goal=[8.0, 5.0],
    obstacles=[(2.0, 8.0, 0.5), (11.0, 2.0, 0.8)],
)


def square_env(**overrides: object) -> FormationEnv:
    return FormationEnv(FormationConfig.task("ch5-bearing", n_agents=4, **overrides), render_mode="rgb_array")


def test_every_attribute_exists_from_init() -> None:
    """reset(), step() and render() only set attributes __init__ already made."""
    env = square_env()
    before = set(vars(env))
    env.reset(seed=0, options={"scenario": SQUARE})
    assert set(vars(env)) == before
    env.step({agent: np.zeros(2) for agent in env.agents})
    env.render()
    assert set(vars(env)) == before
    env.reset(seed=1)  # a drawn scenario
    assert set(vars(env)) == before


def test_state_before_reset_is_an_error() -> None:
    env = square_env()
    with pytest.raises(RuntimeError, match="before reset"):
        env.team_state()
    with pytest.raises(RuntimeError, match="before reset"):
        env.state()
    assert env.state_space.shape == (4 * 2 + 4 * 2 + 2 + 4 * 3 + 1,)  # the space is known before any reset


def test_team_state_after_reset_is_the_scenario() -> None:
    env = square_env()
    with pytest.raises(RuntimeError, match="before reset"):
        env.team_state()
    env.reset(seed=0, options={"scenario": SQUARE})
    state = env.team_state()
    assert state.step == 0 and state.n_agents == 4
    np.testing.assert_array_equal(state.positions, SQUARE.agent_positions)
    np.testing.assert_array_equal(state.velocities, np.zeros((4, 2)))
    np.testing.assert_array_equal(state.goal, [8.0, 5.0])
    np.testing.assert_array_equal(state.obstacles, SQUARE.obstacles)
    np.testing.assert_array_equal(state.neighbours, [[3, 1], [0, 2], [1, 3], [2, 0]])  # ring: i - 1, i + 1 (mod 4)
    np.testing.assert_array_equal(state.centroid, [5.0, 5.0])
    assert state.goal_distance == 3.0
    np.testing.assert_array_equal(state.contacts_agent, 0)
    np.testing.assert_array_equal(state.contacts_obstacle, 0)
    # a unit square: every neighbour 1 m away and the interior angle the reference 90 deg; but the reference square
    # stands on a vertex (reference bearings at 45 + k 90 deg), so each bearing is 45 deg off: |g_ref - g| = 2 sin 22.5 deg
    np.testing.assert_allclose(state.neighbour_distances, np.ones((4, 2)))
    np.testing.assert_allclose(state.angle_errors_deg, 0.0, atol=1e-9)
    np.testing.assert_allclose(state.bearing_errors, 2 * math.sin(math.radians(22.5)))
    np.testing.assert_array_equal(state.neighbour_distance_errors, 0.0)  # d_ref 1.5 m: no neighbour beyond it
    assert state.lidar_obstacles.shape == state.lidar_agents.shape == (4, 90)


def test_team_state_is_a_frozen_copy() -> None:
    env = square_env()
    env.reset(seed=0, options={"scenario": SQUARE})
    old = env.team_state()
    assert not old.positions.flags.writeable and not old.lidar_obstacles.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        old.positions[0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        old.step = 3  # type: ignore[misc]
    for _ in range(3):
        env.step({agent: np.array([1.0, 0.0]) for agent in env.agents})
    new = env.team_state()
    assert (old.step, new.step) == (0, 3)
    np.testing.assert_array_equal(old.positions, SQUARE.agent_positions)  # the old snapshot did not move
    assert (new.positions[:, 0] > old.positions[:, 0]).all()  # every agent pushed right moved right
    np.testing.assert_allclose(new.velocities, np.tile([0.05, 0.0], (4, 1)))  # full force: v_max in one step
    assert new.goal_distance == pytest.approx(3.0 - 3 * 0.05 * 0.3)  # three steps of v_max dt to the right


def test_team_state_copies_the_arrays_it_is_given() -> None:
    """A state built by hand does not alias the caller's arrays, and its neighbour distances are the ring's sides."""
    positions = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])  # a 3-4-5 right triangle
    zeros = np.zeros(3)
    state = TeamState(
        step=7,
        positions=positions,
        velocities=np.zeros((3, 2)),
        goal=np.array([9.0, 9.0]),
        obstacles=np.zeros((0, 3)),
        neighbours=np.array([[2, 1], [0, 2], [1, 0]]),
        contacts_agent=zeros,
        contacts_obstacle=zeros,
        angle_errors_deg=zeros,
        bearing_errors=zeros,
        neighbour_distance_errors=zeros,
        centroid=positions.mean(axis=0),
        goal_distance=1.0,
    )
    positions[0] = [100.0, 100.0]
    np.testing.assert_array_equal(state.positions[0], [0.0, 0.0])
    assert state.lidar_obstacles is None and state.lidar_agents is None and state.n_agents == 3
    # agent 0: to agent 2 (hypotenuse 5), to agent 1 (3); agent 1: 3 and 4; agent 2: 4 and 5
    np.testing.assert_allclose(state.neighbour_distances, [[5.0, 3.0], [3.0, 4.0], [4.0, 5.0]])


def test_neighbour_distances_of_a_triangle() -> None:
    env = FormationEnv(FormationConfig.task("ch4-individual"))
    triangle = Scenario(agent_positions=[[2.0, 2.0], [5.0, 2.0], [2.0, 6.0]], goal=[8.0, 5.0])
    env.reset(seed=0, options={"scenario": triangle})
    # sides 3, 5 (the 3-4-5 hypotenuse) and 4; agent 0's neighbours are agent 2 (4 m) and agent 1 (3 m)
    np.testing.assert_allclose(env.team_state().neighbour_distances, [[4.0, 3.0], [3.0, 5.0], [5.0, 4.0]])


def test_global_state_vector_reads_back_field_by_field() -> None:
    env = square_env()
    env.reset(seed=0, options={"scenario": SQUARE})
    for _ in range(2):
        env.step({agent: np.array([0.0, -1.0]) for agent in env.agents})
    vector, state, layout = env.state(), env.team_state(), env.state_layout
    assert vector.dtype == np.float32 and vector.shape == env.state_space.shape == (4 * 2 + 4 * 2 + 2 + 4 * 3 + 1,)
    assert env.state_space.contains(vector)
    np.testing.assert_array_equal(vector[layout["positions"]], state.positions.ravel().astype(np.float32))
    np.testing.assert_array_equal(vector[layout["velocities"]], np.tile([0.0, -0.05], 4).astype(np.float32))
    np.testing.assert_array_equal(vector[layout["goal"]], [8.0, 5.0])
    obstacles = np.array([2.0, 8.0, 0.5, 11.0, 2.0, 0.8, 0, 0, 0, 0, 0, 0], dtype=np.float32)
    np.testing.assert_array_equal(vector[layout["obstacles"]], obstacles)
    np.testing.assert_array_equal(vector[layout["step"]], [2.0])
    assert list(layout) == ["positions", "velocities", "goal", "obstacles", "walls", "step"]
    assert layout["walls"] == slice(layout["obstacles"].stop, layout["obstacles"].stop)  # no walls in the curriculum


def test_state_has_room_for_every_curriculum_stage() -> None:
    """Stage 1-2 place the most obstacles: 3 large and 1 small (thesis 4.3, 5.3)."""
    for preset in ("ch4-individual", "ch5-bearing"):
        config = FormationConfig.task(preset)
        assert scene_slots(config) == (4, 0)
        env = FormationEnv(config)
        for stage in (1, 2, 3):
            env.set_stage(stage)
            for seed in range(5):
                env.reset(seed=seed)
                assert env.state_space.contains(env.state())
    crowded = Scenario(SQUARE.agent_positions, SQUARE.goal, [(1.0 + 2 * k, 8.5, 0.3) for k in range(5)])
    env = square_env()
    env.reset(seed=0, options={"scenario": crowded})
    with pytest.raises(ValueError, match=r"room for 4 obstacles .* this scenario has 5"):
        env.state()


def test_pettingzoo_state_test() -> None:
    """PettingZoo's own state checks, through its AEC conversion (a whole truncated episode) and the parallel API."""
    config = FormationConfig.task("ch5-bearing", n_agents=4, stage=3, max_steps=40)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # state_test only warns about most problems: make them failures
        state_test(parallel_to_aec(FormationEnv(config)), FormationEnv(config), num_cycles=50)


def test_rendering_is_a_pure_function_of_the_state() -> None:
    env = square_env()
    env.reset(seed=0, options={"scenario": SQUARE})
    env.step({agent: np.array([0.5, 0.5]) for agent in env.agents})
    state = env.team_state()
    frame = env.render()
    np.testing.assert_array_equal(render_frame(state, env.config), frame)
    # rebuilt by hand from the same arrays, as from a recording: no lidar readings
    fields = [field.name for field in dataclasses.fields(TeamState) if not field.name.startswith("lidar")]
    without_lidar = TeamState(**{name: getattr(state, name) for name in fields})
    assert without_lidar.lidar_obstacles is None and without_lidar.lidar_agents is None
    np.testing.assert_array_equal(render_frame(without_lidar, env.config), frame)
    with pytest.raises(ValueError, match="lidar"):
        render_frame(without_lidar, env.config, draw_lidar=True)
    assert (render_frame(state, env.config, draw_lidar=True) != frame).any()  # the obstacle at (2, 8) is in range
    # an agent moved by hand moves in the picture: the frame is drawn from the state given, nothing else
    moved = dataclasses.replace(state, positions=state.positions + np.array([[1.0, 0.0], [0, 0], [0, 0], [0, 0]]))
    assert (render_frame(moved, env.config) != frame).any()


def test_contacts_of_the_last_step_are_in_the_state() -> None:
    """Agent 0 pushed into the left wall touches it; agent 1, pushed after it, touches agent 0 in the second step
    (0.15 m per step at v_max 0.5 m/s, dt 0.3 s)."""
    env = square_env(v_max=0.5)
    touching = Scenario([[0.25, 5.0], [0.75, 5.0], [5.0, 7.0], [5.0, 3.0]], goal=[12.0, 5.0])
    env.reset(seed=0, options={"scenario": touching})
    push = {"agent_0": [-1.0, 0.0], "agent_1": [-1.0, 0.0], "agent_2": [0.0, 0.0], "agent_3": [0.0, 0.0]}
    for _ in range(2):
        env.step({agent: np.array(action) for agent, action in push.items()})
    state = env.team_state()
    np.testing.assert_array_equal(state.contacts_obstacle, [1, 0, 0, 0])  # agent 0 on the left wall
    np.testing.assert_array_equal(state.contacts_agent, [1, 1, 0, 0])  # agents 0 and 1, counted once each
    assert 0.17 < state.positions[0, 0] < 0.21  # on the wall (agent 1 presses it in by about a centimetre)


@pytest.mark.parametrize("scenes", ["passage", "corridor", "trap", "clutter", "mixed"])
def test_state_holds_every_scene_family(scenes: str) -> None:
    """Each family's scenes fit the state's circle and wall slots, and the walls are written in their slots."""
    config = FormationConfig.task("ch5-bearing", scenes=scenes, stage=3)
    env = FormationEnv(config)
    circles, walls = scene_slots(config)
    layout = state_layout(config)
    for seed in range(6):
        env.reset(seed=seed)
        state = env.state()
        assert env.state_space.contains(state)
        written = state[layout["walls"]].reshape(walls, 5)
        team = env.team_state()
        np.testing.assert_array_equal(written[: len(team.walls)], team.walls.astype(np.float32))
        assert not written[len(team.walls) :].any()
    assert (circles, walls) == {"passage": (0, 2), "corridor": (0, 4), "trap": (0, 3), "clutter": (12, 0), "mixed": (12, 4)}[
        scenes
    ]
    walls_in_a_row = [[1.0, 0.5 + 0.3 * k, 2.0, 0.5 + 0.3 * k, 0.1] for k in range(walls + 1)]
    env.reset(options={"scenario": Scenario(start_formation(config, np.array([7.5, 5.0])), [12.0, 5.0], walls=walls_in_a_row)})
    with pytest.raises(ValueError, match=rf"room for {walls} walls .* this scenario has {walls + 1}"):
        env.state()
