"""Moving obstacles: paths and bounces against hand-computed motion, walkers against navground's own behaviours, the
world's kinematic bodies, the lidar against an independent ray cast, and bad movers refused."""

from __future__ import annotations

import math

import navground.core as crowd_core
import numpy as np
import pymunk
import pytest

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import FormationEngine
from sb3_formation.env.movers import CROWD_SENSING_RANGE, Mover, MovingObstacles
from sb3_formation.env.scenarios import Scenario, start_formation
from sb3_formation.env.sensors import OBSTACLE_CHANNEL
from sb3_formation.ros.scans import merged_scan

CONFIG = FormationConfig()  # n = 6, 15 m x 10 m, R_a = 0.2 m, v_max = 0.05 m/s, dt = 0.3 s
W, H = CONFIG.world_width, CONFIG.world_height


def test_path_follows_the_closed_polyline_at_its_speed() -> None:
    """Legs of 3, 4 and 5 m (a closed 12 m loop) at 1 m/s, steps of 0.5 s: after k steps the mover is 0.5 k m along
    the loop; at 4 m it is at (5, 3), at 7 m at the corner (5, 6), at 10 m 3/5 of the way back from (5, 6) to (2, 2)."""
    movers = MovingObstacles((Mover(0.3, [[2, 2], [5, 2], [5, 6]], 1.0, "path"),), 0.5, W, H)
    expected = {8: (5.0, 3.0), 14: (5.0, 6.0), 20: (3.2, 3.6), 24: (2.0, 2.0), 25: (2.5, 2.0)}
    previous = movers.positions.copy()
    for step in range(1, 26):
        velocity = movers.step(np.zeros((0, 2)), np.zeros((0, 2)))
        assert velocity[0] == pytest.approx((movers.positions[0] - previous[0]) / 0.5, abs=1e-12)
        previous = movers.positions.copy()
        if step in expected:
            assert movers.positions[0] == pytest.approx(expected[step], abs=1e-12), step
    assert movers.velocities[0] == pytest.approx([1.0, 0.0], abs=1e-12)  # on the first leg again


def test_bounce_mirrors_at_the_border() -> None:
    """A 0.5 m mover at (1, 1) heading (1, 1) at sqrt(2) m/s in a 4 m x 3 m world, steps of 1 s: (2, 2), then y
    mirrors at 2.5 ((3, 2)), x at 3.5 ((3, 1)), y at 0.5 ((2, 1)); the step's velocity is the chord of each step."""
    movers = MovingObstacles((Mover(0.5, [[1, 1], [2, 2]], math.sqrt(2), "bounce"),), 1.0, 4.0, 3.0)
    for position, chord in [((2, 2), (1, 1)), ((3, 2), (1, 0)), ((3, 1), (0, -1)), ((2, 1), (-1, 0))]:
        assert movers.step(np.zeros((0, 2)), np.zeros((0, 2)))[0] == pytest.approx(chord, abs=1e-12)
        assert movers.positions[0] == pytest.approx(position, abs=1e-12)


def _library_velocity(position, velocity, goal, neighbours) -> np.ndarray:
    """What navground's ORCA behaviour, asked on its own, commands a walker (radius 0.3 m, 1 m/s) that sees
    ``neighbours`` and the world's border (navground's bounded sensing passes every wall, near or far)."""
    behavior = crowd_core.behaviors.ORCABehavior(
        kinematics=crowd_core.kinematics.OmnidirectionalKinematics(max_speed=1.0), radius=0.3
    )
    behavior.optimal_speed = 1.0
    behavior.position, behavior.velocity = position, velocity
    behavior.target = crowd_core.Target.Point(np.asarray(goal, dtype=float), 0.25)
    behavior.environment_state.neighbors = neighbours
    corners = [(0.0, 0.0), (W, 0.0), (W, H), (0.0, H)]
    behavior.environment_state.line_obstacles = [
        crowd_core.LineSegment(start, end) for start, end in zip(corners, corners[1:] + corners[:1])
    ]
    return np.array(behavior.compute_cmd(0.3).velocity, dtype=float)


def test_walker_velocities_are_the_crowd_model_s_own() -> None:
    """A reacting walker's velocity in every step is what navground's ORCA behaviour commands for the same state
    (the agent it sees as a neighbour with its position and velocity), to single precision; a walker that does not
    react walks as if the agent were not there."""
    mover = Mover(0.3, [[4, 5], [12, 5]], 1.0, "walk", reacts=True)
    movers = MovingObstacles((mover,), 0.3, W, H, agent_radius=0.2)
    agent, agent_velocity = np.array([[5.5, 5.05]]), np.array([[-0.05, 0.0]])
    for _ in range(8):
        neighbour = crowd_core.Neighbor(agent[0], 0.2, agent_velocity[0], 0)
        position = movers.positions[0]
        assert math.dist(position, agent[0]) < CROWD_SENSING_RANGE  # the walker sees the agent
        expected = _library_velocity(position, movers.velocities[0], (12, 5), [neighbour])
        assert movers.step(agent, agent_velocity)[0] == pytest.approx(expected, abs=1e-4)
        agent = agent + 0.3 * agent_velocity
    assert abs(movers.positions[0, 1] - 5.0) > 0.05  # it stepped aside
    blind = Mover(0.3, [[3, 5], [12, 5]], 1.0, "walk", reacts=False)
    alone, beside = (MovingObstacles((blind,), 0.3, W, H, agent_radius=0.2) for _ in range(2))
    for _ in range(8):
        alone.step(np.zeros((0, 2)), np.zeros((0, 2)))
        beside.step(np.array([[5.5, 5.05]]), np.zeros((1, 2)))
    assert np.array_equal(alone.positions, beside.positions)
    assert alone.positions[0, 1] == pytest.approx(5.0, abs=1e-5)  # straight at the agent's place


def _engine(movers: tuple[Mover, ...], centroid=(3.0, 5.0)) -> FormationEngine:
    engine = FormationEngine([CONFIG])
    scenario = Scenario(start_formation(CONFIG, np.array(centroid)), np.array([12.0, 5.0]), movers=movers)
    engine.reset(0, seed=0, scenario=scenario)
    return engine


def test_world_moves_kinematic_bodies_to_the_model_s_positions() -> None:
    """The world's mover bodies end each step where the model put them, and the team's state lists them after the
    static obstacles with their velocities."""
    movers = (Mover(0.5, [[7, 1], [7, 9]], 0.05, "path"), Mover(0.4, [[10, 3], [11, 4]], 0.07, "bounce"))
    engine = _engine(movers)
    world = engine.worlds[0]
    assert world is not None
    for _ in range(20):
        engine.step(np.zeros((CONFIG.n_agents, 2)))
    bodies = np.array([tuple(body.position) for body in world._mover_bodies])
    assert bodies == pytest.approx(world.movers.positions, abs=1e-9)
    assert world.movers.positions[0] == pytest.approx([7.0, 1.0 + 20 * 0.3 * 0.05], abs=1e-12)
    state = engine.team_state(0)
    assert state.obstacles[:, :2] == pytest.approx(world.movers.positions, abs=0)
    assert state.obstacle_velocities == pytest.approx(np.array([[0.0, 0.05], [0.07 / math.sqrt(2)] * 2]), abs=1e-12)


def test_a_mover_pushes_an_agent_and_counts_as_an_obstacle_contact() -> None:
    """A path mover driven through the team's place at 0.1 m/s pushes the agents it meets (kinematic bodies are never
    pushed back) and each touch counts on the obstacle column."""
    engine = _engine((Mover(0.4, [[3, 1], [3, 9]], 0.1, "path"),))
    touched = 0
    for _ in range(100):
        touched += int(engine.step(np.zeros((CONFIG.n_agents, 2))).contacts[:, 1].sum())
    world = engine.worlds[0]
    assert world is not None
    assert touched > 0
    assert world.movers.positions[0] == pytest.approx([3.0, 1.0 + 100 * 0.03], abs=1e-12)  # never slowed


def test_the_lidar_sees_a_moving_obstacle_where_a_ray_cast_puts_it() -> None:
    """After every step, each agent's obstacle-channel readings equal Pymunk's own ray cast against the mover at the
    model's position (and the border), from the agent's surface over the lidar range; the scans a ROS 2 simulator
    publishes (:func:`merged_scan`, seeing through the agents) put it at the same place."""
    engine = _engine((Mover(0.5, [[5.9, 3.0], [5.9, 8.5]], 0.05, "path"),), centroid=(4.0, 5.0))
    space = pymunk.Space()
    mover = pymunk.Circle(space.static_body, 0.5, (0.0, 0.0))
    corners = [(0, 0), (W, 0), (W, H), (0, H)]
    space.add(mover, *(pymunk.Segment(space.static_body, a, b, 0.0) for a, b in zip(corners, corners[1:] + corners[:1])))
    lidar = engine.lidars[0]
    seen = 0
    for _ in range(40):
        engine.step(np.zeros((CONFIG.n_agents, 2)))
        world = engine.worlds[0]
        assert world is not None
        mover.unsafe_set_offset(tuple(world.movers.positions[0]))
        space.reindex_static()
        readings = engine.episodes.lidar[OBSTACLE_CHANNEL, : CONFIG.n_agents]
        published = merged_scan(lidar, engine.latest.positions, stopped_by_agents=False)
        seen_by_ros = np.where(readings < 1.0, readings * CONFIG.lidar_range + CONFIG.agent_radius, np.inf)
        np.testing.assert_allclose(published, seen_by_ros, rtol=0, atol=1e-9)
        for agent, position in enumerate(engine.latest.positions):
            for ray, direction in enumerate(lidar.directions):
                start = position + CONFIG.agent_radius * direction
                end = start + CONFIG.lidar_range * direction
                hit = space.segment_query_first(tuple(start), tuple(end), 0.0, pymunk.ShapeFilter())
                expected = 1.0 if hit is None else hit.alpha
                seen += hit is not None and hit.shape is mover
                assert readings[agent, ray] == pytest.approx(expected, abs=1e-9)
    assert seen > 0


def test_the_same_seed_gives_the_same_crowd() -> None:
    """Two engines with the same scenario of walkers play the same episode, bit for bit."""
    walkers = tuple(Mover(0.3, [[x, 1.0], [x, 9.0]], 0.06, "walk", reacts=True) for x in (5.0, 6.0, 7.0))
    runs = []
    for _ in range(2):
        engine = _engine(walkers)
        actions = np.tile([[1.0, 0.0]], (CONFIG.n_agents, 1))
        steps = [engine.step(actions) for _ in range(30)]
        world = engine.worlds[0]
        assert world is not None
        runs.append((np.concatenate([step.positions for step in steps]), world.movers.positions.copy()))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"radius": 0.3, "waypoints": [[1, 1]], "speed": 1.0}, r"shape \(p, 2\) with p >= 2"),
        ({"radius": 0.3, "waypoints": [[1, 1], [np.nan, 2]], "speed": 1.0}, "NaN"),
        ({"radius": 0.0, "waypoints": [[1, 1], [2, 2]], "speed": 1.0}, "Mover.radius=0.0"),
        ({"radius": 0.3, "waypoints": [[1, 1], [2, 2]], "speed": -1.0}, "Mover.speed=-1.0"),
        ({"radius": 0.3, "waypoints": [[1, 1], [2, 2]], "speed": 1.0, "motion": "fly"}, "Mover.motion='fly'"),
        ({"radius": 0.3, "waypoints": [[1, 1], [1, 1]], "speed": 1.0}, "repeats a point"),
        ({"radius": 0.3, "waypoints": [[1, 1], [2, 2]], "speed": 1.0, "behavior": "Boids"}, "Mover.behavior='Boids'"),
    ],
)
def test_bad_movers_are_refused(kwargs, message) -> None:
    with pytest.raises(ValueError, match=message):
        Mover(**kwargs)


def test_scenarios_refuse_movers_that_do_not_fit() -> None:
    """A mover starting on an agent, a waypoint outside the world, and walkers that react and walkers that do not."""
    positions, goal = start_formation(CONFIG, np.array([3.0, 5.0])), np.array([12.0, 5.0])
    on_agent = Scenario(positions, goal, movers=(Mover(0.3, [positions[0], [9, 9]], 0.1),))
    with pytest.raises(ValueError, match="agent_0 overlaps mover 0's start"):
        on_agent.validate(CONFIG)
    outside = Scenario(positions, goal, movers=(Mover(0.3, [[9, 9], [16, 9]], 0.1),))
    with pytest.raises(ValueError, match=r"mover 0's waypoint at \(16.000, 9.000\) m is outside the world"):
        outside.validate(CONFIG)
    walkers = (Mover(0.3, [[9, 9], [9, 1]], 0.1, "walk", reacts=True), Mover(0.3, [[8, 9], [8, 1]], 0.1, "walk"))
    with pytest.raises(ValueError, match="all react to the agents or all not react"):
        Scenario(positions, goal, movers=walkers)
