"""Tests of the two-channel lidar, against readings computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_formation.env.geometry import ring_neighbours
from sb3_formation.env.sensors import Lidar
from sb3_formation.env.shapes import shape_gaps

R = 0.2  # agent radius (m)
RANGE = 1.5  # lidar range (m)
W, H = 15.0, 10.0  # world (m)
FAR = [[12.0, 8.0], [12.0, 2.0], [9.0, 8.0], [9.0, 2.0]]  # parking spots far from (5, 5) and from each other


def lidar(n_agents: int, n_rays: int = 90, obstacles: list[list[float]] | None = None) -> Lidar:
    """A lidar for a ring of n_agents in the 15 m x 10 m world."""
    sensor = Lidar(n_rays, RANGE, R, W, H, ring_neighbours(n_agents))
    if obstacles is not None:
        sensor.set_obstacles(np.array(obstacles, dtype=float))
    return sensor


def positions(first: list[list[float]], n_agents: int) -> np.ndarray:
    """The given agent positions, the remaining agents parked far away."""
    return np.array(first + FAR[: n_agents - len(first)], dtype=float)


def chord_reading(angle_deg: float, centre: tuple[float, float], radius: float, origin=(5.0, 5.0)) -> float:
    """Hand formula: t = u.(c-p) - sqrt((u.(c-p))^2 - |c-p|^2 + r^2), reading (t - R)/range (1 on a miss)."""
    ux, uy = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    ox, oy = centre[0] - origin[0], centre[1] - origin[1]
    projection = ux * ox + uy * oy
    discriminant = projection**2 - (ox**2 + oy**2) + radius**2
    if discriminant < 0:
        return 1.0
    return min((projection - math.sqrt(discriminant) - R) / RANGE, 1.0)


def test_obstacle_straight_ahead() -> None:
    """Agent (5,5), obstacle (6,5) r=0.3: ray 0 reads (1 - 0.3 - 0.2)/1.5 = 1/3; the ray at 180 deg reads 1."""
    obstacles, agents = lidar(3, obstacles=[[6.0, 5.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles.shape == agents.shape == (3, 90)
    assert obstacles[0, 0] == pytest.approx((1.0 - 0.3 - 0.2) / 1.5, abs=1e-12)
    assert obstacles[0, 45] == 1.0  # 45 * 4 = 180 deg
    np.testing.assert_array_equal(agents, 1.0)  # n = 3: every other agent is a neighbour


def test_obstacle_off_centre_rays() -> None:
    """Obstacle (6,5) r=0.3 is 17.46 deg wide each side (asin 0.3): rays at +-4 .. +-16 deg hit it, +-20 deg miss.

    Ray at 4 deg: u.(c-p) = cos 4 = 0.997564; disc = 0.09 - sin^2 4 = 0.085134; t = 0.997564 - 0.291777 = 0.705787;
    reading (0.705787 - 0.2)/1.5 = 0.337191. Grazing ray at 16 deg: disc = 0.09 - sin^2 16 = 0.014024;
    t = 0.961262 - 0.118423 = 0.842839; reading 0.428559.
    """
    obstacles, _ = lidar(3, obstacles=[[6.0, 5.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 1] == pytest.approx(0.337191, abs=1e-6)
    assert obstacles[0, 4] == pytest.approx(0.428559, abs=1e-6)
    for ray in (1, 2, 3, 4):
        expected = chord_reading(4.0 * ray, (6.0, 5.0), 0.3)
        assert obstacles[0, ray] == pytest.approx(expected, abs=1e-12)
        assert obstacles[0, 90 - ray] == pytest.approx(expected, abs=1e-12)  # symmetric about the x axis
    assert obstacles[0, 5] == 1.0  # 20 deg: sin 20 = 0.342 > 0.3, a miss
    assert obstacles[0, 85] == 1.0
    assert (obstacles[0, 6:85] == 1.0).all()


def test_obstacle_at_90_degrees_exact_ray() -> None:
    """8 rays (45 deg apart): ray 2 points at 90 deg; obstacle (5, 6.2) r=0.5 reads (1.2 - 0.5 - 0.2)/1.5 = 1/3.

    Its half-width asin(0.5 / 1.2) = 24.6 deg < 45 deg, so rays 1 and 3 miss.
    """
    obstacles, _ = lidar(3, n_rays=8, obstacles=[[5.0, 6.2, 0.5]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles.shape == (3, 8)
    assert obstacles[0, 2] == pytest.approx(1.0 / 3.0, abs=1e-12)
    np.testing.assert_array_equal(obstacles[0, [0, 1, 3, 4, 5, 6, 7]], 1.0)


def test_obstacle_at_90_degrees_between_rays() -> None:
    """90 rays: an obstacle at 90 deg lies between rays 22 (88 deg) and 23 (92 deg), both 2 deg off-centre.

    Obstacle (5, 6) r=0.3: u.(c-p) = cos 2 = 0.999391; disc = 0.09 - sin^2 2 = 0.088782; t = 0.999391 - 0.297963
    = 0.701428; reading (0.701428 - 0.2)/1.5 = 0.334285.
    """
    obstacles, _ = lidar(3, obstacles=[[5.0, 6.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 22] == pytest.approx(0.334285, abs=1e-6)
    assert obstacles[0, 23] == pytest.approx(0.334285, abs=1e-6)
    assert obstacles[0, 22] == pytest.approx(chord_reading(88.0, (5.0, 6.0), 0.3), abs=1e-12)
    assert obstacles[0, 0] == 1.0
    assert obstacles[0, 67] == 1.0  # 268 deg, pointing away


def test_hidden_neighbour_and_visible_non_neighbour() -> None:
    """n = 5: agent 0 does not see its neighbour 1 at (6,5) ahead, but sees agent 2 at (4,5) behind.

    Agent 2 reading on ray 45 (180 deg): (1 - 0.2 - 0.2)/1.5 = 0.4. Agents never show on the obstacle channel.
    """
    team = positions([[5.0, 5.0], [6.0, 5.0], [4.0, 5.0]], 5)
    obstacles, agents = lidar(5).scan(team)
    assert agents.shape == (5, 90)
    assert agents[0, 0] == 1.0  # neighbour 1 hidden
    assert agents[0, 45] == pytest.approx(0.4, abs=1e-12)
    assert agents[0, 44] == pytest.approx(chord_reading(176.0, (4.0, 5.0), R), abs=1e-12)
    np.testing.assert_array_equal(obstacles[:3], 1.0)  # no obstacles, walls 4 m or more away
    # agent 2's neighbours are 1 and 3: it sees agent 0 ahead at 0.4, and agent 1 behind it is hidden anyway
    assert agents[2, 0] == pytest.approx(0.4, abs=1e-12)
    # agent 1's neighbours are 0 and 2: agent 1 sees nothing near
    np.testing.assert_array_equal(agents[1], 1.0)


def test_neighbour_hidden_even_in_contact() -> None:
    """n = 6: neighbour 5 touching agent 0 stays hidden; non-neighbour 3 touching it reads 0 on the ray at it."""
    team = positions([[5.0, 5.0], [9.0, 2.0], [9.0, 8.0], [5.0, 5.4], [12.0, 8.0], [5.0, 4.6]], 6)
    _, agents = lidar(6).scan(team)
    # agent 3 at 90 deg, centre distance 0.4 = 2R: between rays 22 and 23 (88 and 92 deg)
    assert agents[0, 22] == pytest.approx(chord_reading(88.0, (5.0, 5.4), R), abs=1e-12)
    assert agents[0, 22] < 0.01
    # agent 5 (neighbour) at 270 deg, touching: hidden
    np.testing.assert_array_equal(agents[0, 60:75], 1.0)


def test_channels_do_not_occlude_each_other() -> None:
    """n = 5, along ray 0 of agent 0 at (5,5): a non-neighbour behind an obstacle and an obstacle behind it.

    Obstacle (6,5) r=0.2: (1 - 0.2 - 0.2)/1.5 = 0.4; agent 2 at (6.5,5): (1.5 - 0.2 - 0.2)/1.5 = 11/15.
    """
    team = positions([[5.0, 5.0], [9.0, 8.0], [6.5, 5.0]], 5)
    obstacles, agents = lidar(5, obstacles=[[6.0, 5.0, 0.2]]).scan(team)
    assert obstacles[0, 0] == pytest.approx(0.4, abs=1e-12)
    assert agents[0, 0] == pytest.approx(11.0 / 15.0, abs=1e-12)
    # agent in front of an obstacle: agent 2 at (5.6,5), obstacle (6.5,5) r=0.3
    team = positions([[5.0, 5.0], [9.0, 8.0], [5.6, 5.0]], 5)
    obstacles, agents = lidar(5, obstacles=[[6.5, 5.0, 0.3]]).scan(team)
    assert obstacles[0, 0] == pytest.approx((1.5 - 0.3 - 0.2) / 1.5, abs=1e-12)  # 2/3
    assert agents[0, 0] == pytest.approx((0.6 - 0.2 - 0.2) / 1.5, abs=1e-12)  # 2/15


def test_nearest_circle_wins() -> None:
    """Two obstacles on ray 0: the nearer, (5.8,5) r=0.1, gives (0.8 - 0.1 - 0.2)/1.5 = 1/3."""
    obstacles, _ = lidar(3, obstacles=[[6.3, 5.0, 0.3], [5.8, 5.0, 0.1]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 0] == pytest.approx(1.0 / 3.0, abs=1e-12)


def test_out_of_range_obstacle() -> None:
    """Obstacle (7,5) r=0.3: surface gap 2 - 0.3 - 0.2 = 1.5 reads exactly 1; (7.1,5) is beyond range and reads 1."""
    obstacles, _ = lidar(3, obstacles=[[7.0, 5.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 0] == pytest.approx(1.0, abs=1e-12)
    obstacles, _ = lidar(3, obstacles=[[7.1, 5.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    np.testing.assert_array_equal(obstacles[0], 1.0)


def test_walls() -> None:
    """8 rays, 15 x 10 world.

    Agent 0 at (14.5,5): ray 0 reads (15 - 14.5 - 0.2)/1.5 = 0.2; ray 1 (45 deg) meets x = 15 after 0.5/cos 45
    = 0.707107, reading (0.707107 - 0.2)/1.5 = 0.338071; ray 4 (180 deg) reads 1.
    Agent 1 at (14,9): ray 1 goes to the corner (15,10), sqrt(2) away: (1.414214 - 0.2)/1.5 = 0.809476;
    rays 0 and 2 meet the walls 1 m away: 0.8/1.5.
    """
    obstacles, agents = lidar(3, n_rays=8).scan(np.array([[14.5, 5.0], [14.0, 9.0], [7.0, 5.0]]))
    assert obstacles[0, 0] == pytest.approx(0.2, abs=1e-12)
    assert obstacles[0, 1] == pytest.approx((0.5 * math.sqrt(2.0) - 0.2) / 1.5, abs=1e-12)
    assert obstacles[0, 1] == pytest.approx(0.338071, abs=1e-6)
    assert obstacles[0, 4] == 1.0
    assert obstacles[1, 1] == pytest.approx((math.sqrt(2.0) - 0.2) / 1.5, abs=1e-12)
    assert obstacles[1, 1] == pytest.approx(0.809476, abs=1e-6)
    assert obstacles[1, 0] == pytest.approx(0.8 / 1.5, abs=1e-12)
    assert obstacles[1, 2] == pytest.approx(0.8 / 1.5, abs=1e-12)
    assert obstacles[1, 4] == 1.0
    np.testing.assert_array_equal(obstacles[2], 1.0)  # 5 m or more from every wall
    np.testing.assert_array_equal(agents, 1.0)  # walls are not on the agent channel


def test_walls_ninety_rays() -> None:
    """90 rays, agent at (14.5,5): ray 0 reads 0.3/1.5 = 0.2; ray 45 (180 deg) reads 1; ray 22 (88 deg) meets
    y = 10 after 5/sin 88 > range and x = 15 after 0.5/cos 88 = 14.33 m: 1.

    Ray 2 (8 deg): x = 15 after 0.5/cos 8 = 0.504914: (0.504914 - 0.2)/1.5 = 0.203276.
    """
    obstacles, _ = lidar(3).scan(positions([[14.5, 5.0]], 3))
    assert obstacles[0, 0] == pytest.approx(0.2, abs=1e-12)
    assert obstacles[0, 45] == 1.0
    assert obstacles[0, 22] == 1.0
    assert obstacles[0, 2] == pytest.approx(0.203276, abs=1e-6)


def test_agent_sunk_into_obstacle_reads_zero() -> None:
    """Agent (5,5), obstacle (5.4,5) r=0.3 overlapping it.

    The surface point at angle a, (0.2 cos a, 0.2 sin a), is inside the circle iff 0.2 - 0.16 cos a < 0.09, i.e.
    cos a > 0.6875, a < 46.57 deg: rays within +-44 deg read 0. Ray at 48 deg: u.(c-p) = 0.4 cos 48 = 0.267652,
    disc = 0.09 - 0.16 sin^2 48 = 0.001638, t = 0.267652 - 0.040469 = 0.227183, reading 0.018122. Ray at 52 deg:
    0.16 sin^2 52 = 0.0994 > 0.09, a miss.
    """
    obstacles, _ = lidar(3, obstacles=[[5.4, 5.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    np.testing.assert_array_equal(obstacles[0, :12], 0.0)  # 0 .. 44 deg
    np.testing.assert_array_equal(obstacles[0, 79:], 0.0)  # 316 .. 356 deg
    assert obstacles[0, 12] == pytest.approx(0.018122, abs=1e-6)
    assert obstacles[0, 12] == pytest.approx(chord_reading(48.0, (5.4, 5.0), 0.3), abs=1e-12)
    assert obstacles[0, 13] == 1.0


def test_agent_touching_obstacle_reads_zero() -> None:
    """Obstacle (5.5,5) r=0.3 touches the agent's surface: ray 0 reads (0.5 - 0.3 - 0.2)/1.5 = 0."""
    obstacles, _ = lidar(3, obstacles=[[5.5, 5.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert obstacles[0, 1] == pytest.approx(chord_reading(4.0, (5.5, 5.0), 0.3), abs=1e-12)


def test_obstacle_behind_agent_not_seen() -> None:
    """An obstacle entirely behind the ray's start ((4,5) r=0.3, ray 0) is not seen by ray 0; ray 45 reads 0.5/1.5."""
    obstacles, _ = lidar(3, obstacles=[[4.0, 5.0, 0.3]]).scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 0] == 1.0
    assert obstacles[0, 45] == pytest.approx(0.5 / 1.5, abs=1e-12)


def test_set_obstacles_replaces() -> None:
    """set_obstacles replaces the previous obstacles; an empty array leaves only the walls."""
    sensor = lidar(3, obstacles=[[6.0, 5.0, 0.3]])
    team = positions([[5.0, 5.0]], 3)
    assert sensor.scan(team)[0][0, 0] == pytest.approx(1.0 / 3.0, abs=1e-12)
    sensor.set_obstacles(np.zeros((0, 3)))
    np.testing.assert_array_equal(sensor.scan(team)[0][0], 1.0)
    sensor.set_obstacles(np.array([[4.0, 5.0, 0.3]]))
    obstacles, _ = sensor.scan(team)
    assert obstacles[0, 0] == 1.0
    assert obstacles[0, 45] == pytest.approx(1.0 / 3.0, abs=1e-12)


def test_readings_in_unit_interval() -> None:
    """A crowded random scene (overlaps included): every reading lies in [0, 1], and some are 0 and some 1."""
    rng = np.random.default_rng(0)
    n = 6
    obstacles = np.column_stack([rng.uniform(0, W, 40), rng.uniform(0, H, 40), rng.uniform(0.1, 1.0, 40)])
    sensor = lidar(n, obstacles=obstacles.tolist())
    for _ in range(5):
        team = np.column_stack([rng.uniform(0, W, n), rng.uniform(0, H, n)])
        for reading in sensor.scan(team):
            assert reading.shape == (n, 90)
            assert reading.min() >= 0.0
            assert reading.max() <= 1.0
    team = np.array([[5.0, 5.0], [5.1, 5.0], [5.0, 5.1], [5.05, 5.05], [0.05, 0.05], [14.9, 9.9]])
    obstacle_readings, agent_readings = sensor.scan(team)
    for reading in (obstacle_readings, agent_readings):
        assert 0.0 <= reading.min() and reading.max() <= 1.0
    assert (obstacle_readings[4] == 0.0).any()  # sunk into the corner walls
    assert (agent_readings[0] == 0.0).any()  # overlapping non-neighbour 3


# Walls -----------------------------------------------------------------------------------------------------------


def test_wall_face_ahead() -> None:
    """Agent (5,5); wall from (7,3) to (7,7), 0.4 m thick: its face at x = 6.8 is 1.8 - 0.2 = 1.6 m from the agent's
    surface, beyond the 1.5 m range: ray 0 reads 1. Moved to x = 6.5 (face 6.3): ray 0 reads (1.3 - 0.2)/1.5; the
    ray at 20 deg meets the face at t = 1.3 / cos 20 = 1.383424, reading (1.383424 - 0.2)/1.5 = 0.788949 (its point
    y = 5 + 1.3 tan 20 = 5.473 lies on the face)."""
    sensor = lidar(3)
    sensor.set_obstacles(np.zeros((0, 3)), np.array([[7.0, 3.0, 7.0, 7.0, 0.4]]))
    obstacles, _ = sensor.scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 0] == 1.0
    sensor.set_obstacles(np.zeros((0, 3)), np.array([[6.5, 3.0, 6.5, 7.0, 0.4]]))
    obstacles, _ = sensor.scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 0] == pytest.approx(1.1 / 1.5, abs=1e-12)
    assert obstacles[0, 5] == pytest.approx((1.3 / math.cos(math.radians(20)) - 0.2) / 1.5, abs=1e-12)
    assert obstacles[0, 45] == pytest.approx(1.0)  # 180 deg: the border at x = 0 is 5 m away


def test_wall_round_end() -> None:
    """Wall from (6,5) to (9,5), 0.6 m thick: its end is the disc of radius 0.3 around (6,5); ray 0 from (5,5) meets
    it at t = 0.7 (reading (0.7 - 0.2)/1.5 = 1/3), as the circle (6,5) r=0.3 would; so does the ray at 8 deg
    (:func:`chord_reading`)."""
    sensor = lidar(3)
    sensor.set_obstacles(np.zeros((0, 3)), np.array([[6.0, 5.0, 9.0, 5.0, 0.6]]))
    obstacles, _ = sensor.scan(positions([[5.0, 5.0]], 3))
    assert obstacles[0, 0] == pytest.approx(1 / 3, abs=1e-12)
    assert obstacles[0, 2] == pytest.approx(chord_reading(8.0, (6.0, 5.0), 0.3), abs=1e-12)


def test_walls_and_circles_against_pymunk_ray_casts() -> None:
    """On random scenes of circles and walls, every reading equals Pymunk's own ``segment_query_first`` (an
    independent ray cast against capsules and circles) from the agent's surface over the lidar range."""
    import pymunk

    rng = np.random.default_rng(7)
    directions = None
    for _ in range(8):
        circles = np.column_stack([rng.uniform(1, 14, 6), rng.uniform(1, 9, 6), rng.uniform(0.1, 0.8, 6)])
        starts = np.column_stack([rng.uniform(1, 14, 5), rng.uniform(1, 9, 5)])
        angles = rng.uniform(0, 2 * np.pi, 5)
        lengths = rng.uniform(0.5, 4.0, 5)
        ends = starts + lengths[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
        walls = np.column_stack([starts, np.clip(ends, 0, [15, 10]), rng.uniform(0.05, 0.5, 5)])
        space = pymunk.Space()
        for x, y, r in circles:
            space.add(pymunk.Circle(space.static_body, r, (x, y)))
        for x0, y0, x1, y1, thickness in walls:
            space.add(pymunk.Segment(space.static_body, (x0, y0), (x1, y1), thickness / 2))
        corners = [(0, 0), (W, 0), (W, H), (0, H)]
        for a, b in zip(corners, corners[1:] + corners[:1]):
            space.add(pymunk.Segment(space.static_body, a, b, 0.0))
        # agents wherever they keep clear of every shape (so that each ray starts outside them)
        candidates = np.column_stack([rng.uniform(0.3, 14.7, 400), rng.uniform(0.3, 9.7, 400)])
        clear = shape_gaps(candidates, circles, walls, W, H) > R + 1e-6
        agents = candidates[clear][:3]
        sensor = Lidar(36, RANGE, R, W, H, ring_neighbours(3))
        sensor.set_obstacles(circles, walls)
        readings, _ = sensor.scan(agents)
        directions = sensor.directions
        for agent, position in enumerate(agents):
            for ray, direction in enumerate(directions):
                start = position + R * direction
                hit = space.segment_query_first(tuple(start), tuple(start + RANGE * direction), 0.0, pymunk.ShapeFilter())
                expected = 1.0 if hit is None else hit.alpha
                assert readings[agent, ray] == pytest.approx(expected, abs=1e-9)
    assert directions is not None
