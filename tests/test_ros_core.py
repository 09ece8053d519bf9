"""The on-board core of the ROS 2 layer, without ROS: scans resampled onto the task's rays against hand-computed walls,
the two lidar channels and the observation rows against the simulator's, and commands against the dynamics."""

from __future__ import annotations

import math
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.scenarios import Scenario
from sb3_formation.ros.launch import build_parser
from sb3_formation.ros.observer import AgentObserver, TeamView
from sb3_formation.ros.scans import Scan, ScanMount, merged_scan, resample_scan, scan_points, split_scan

#: 36 rays, 10 deg apart; R_a 0.2 m, range 1.5 m (Table 5.1): a ray sees up to 1.7 m from the agent's centre
WALL_TASK = FormationConfig.task("ch5-bearing", lidar_rays=36)
#: the scanners' own reach (m): beyond the task's 1.7 m, so that the resampling, not the scanner, cuts the range
SCANNER_RANGE = 3.0
#: chapter 5's task in its last curriculum stage (obstacles in the way), holonomic and unicycle
STAGE_3 = FormationConfig.task("ch5-bearing", stage=3)
UNICYCLE_STAGE_3 = FormationConfig.task("ch5-bearing", stage=3, dynamics="unicycle")


def beam_angles(angle_min_deg: float, increment_deg: float, count: int) -> np.ndarray:
    """The beams' angles (rad) in the scanner's frame, as a ``LaserScan`` places them."""
    return math.radians(angle_min_deg) + math.radians(increment_deg) * np.arange(count)


def wall_ranges(world_angles: np.ndarray, origin_x: float = 0.0) -> np.ndarray:
    """Ranges (m) to the wall x = 1 m of beams from (origin_x, 0) at ``world_angles``: (1 - origin_x) / cos(angle) in
    front, inf (no return, REP 117) behind or beyond the scanner's reach."""
    cos = np.cos(world_angles)
    ranges = np.full(len(cos), np.inf)
    ahead = cos > 1e-9
    ranges[ahead] = (1.0 - origin_x) / cos[ahead]
    ranges[ranges > SCANNER_RANGE] = np.inf
    return ranges


def corridor_ranges(world_angles: np.ndarray) -> np.ndarray:
    """Ranges (m) from the origin to the walls x = 1 m and x = -1 m (the wall x = 1 m seen along the opposite beam)."""
    ranges: np.ndarray = np.minimum(wall_ranges(world_angles), wall_ranges(world_angles - math.pi))
    return ranges


def expected_readings(config: FormationConfig, both_walls: bool = False) -> np.ndarray:
    """The task's rays against the wall x = 1 m (and x = -1 m): 1 / |cos(theta_k)| - R_a where the wall lies within
    R_a + range of the centre, else the range (nothing). With 36 rays: 0.8 m at 0 deg, 1/cos 50 deg - 0.2 = 1.3557 m
    at +-50 deg, nothing from 60 deg (1/cos 60 deg = 2 m > 1.7 m)."""
    theta = np.arange(config.lidar_rays) * (2.0 * math.pi / config.lidar_rays)
    cos = np.abs(np.cos(theta)) if both_walls else np.cos(theta)
    reach = config.agent_radius + config.lidar_range
    readings = np.full(len(theta), config.lidar_range)
    hit = cos >= 1.0 / reach
    readings[hit] = 1.0 / cos[hit] - config.agent_radius
    return readings


def test_wall_readings_by_hand() -> None:
    """The hand formula itself, for the rays the other tests rely on: 0.8 m ahead, 1/cos 10 deg - 0.2 = 0.815427 m,
    1/cos 50 deg - 0.2 = 1.355724 m, nothing at 60 and 90 deg and behind."""
    readings = expected_readings(WALL_TASK)
    assert readings[[0, 1, 5, 35, 31]] == pytest.approx([0.8, 0.815427, 1.355724, 0.815427, 1.355724], abs=1e-6)
    assert (readings[6:31] == WALL_TASK.lidar_range).all()


@pytest.mark.parametrize(
    ("angle_min_deg", "increment_deg", "count"),
    [(0.0, 1.0, 360), (-180.0, 0.5, 720), (-179.75, 0.7, 514)],
    ids=["1-deg-from-0", "half-deg-from-minus-180", "0.7-deg-off-the-rays"],
)
def test_flat_wall_at_other_resolutions(angle_min_deg: float, increment_deg: float, count: int) -> None:
    """A full-circle scanner at the robot's centre facing +x, at another resolution than the task's 10 deg: each task
    ray reads 1/cos(theta_k) - R_a on the wall and nothing elsewhere, exactly, whether a beam lies along the ray or
    the ray falls between beams (the segment between two returns on a flat wall lies on the wall). The 0.7 deg
    scanner (514 beams from -179.75 deg) has no beam along any task ray: -179.75 + 0.7 k = 10 m has no integer
    solution (20 m = 15 mod 70 would make an even number odd)."""
    angles = beam_angles(angle_min_deg, increment_deg, count)
    scan = Scan(wall_ranges(angles), angles[0], math.radians(increment_deg), 0.05, SCANNER_RANGE)
    readings = resample_scan(scan, ScanMount(), 0.0, WALL_TASK)
    np.testing.assert_allclose(readings, expected_readings(WALL_TASK), rtol=0, atol=1e-12)


def test_flat_wall_ray_between_a_full_scans_last_and_first_beams() -> None:
    """A 0.5 deg full-circle scanner from 0.25 deg: the task's ray 0 lies between its last beam (359.75 deg) and its
    first (0.25 deg), neighbours on the circle; on the flat wall it reads 1 - R_a = 0.8 m, as every other ray reads
    its hand value."""
    angles = beam_angles(0.25, 0.5, 720)
    scan = Scan(wall_ranges(angles), angles[0], math.radians(0.5), 0.05, SCANNER_RANGE)
    readings = resample_scan(scan, ScanMount(), 0.0, WALL_TASK)
    np.testing.assert_allclose(readings[1:], expected_readings(WALL_TASK)[1:], rtol=0, atol=1e-12)
    assert readings[0] == pytest.approx(0.8, abs=1e-12)


def test_270_degree_scanner_reads_nothing_behind() -> None:
    """A 270 deg scanner (-135 to +135 deg, 0.5 deg) between the walls x = 1 m and x = -1 m: the rays it covers read
    1/|cos theta| - R_a (the ray at 130 deg: 1/cos 50 deg - 0.2 = 1.3557 m), the rays from 140 to 220 deg, which
    would read the wall behind (1/cos 40 deg - 0.2 = 1.1054 m at 140 deg), read nothing."""
    angles = beam_angles(-135.0, 0.5, 541)
    scan = Scan(corridor_ranges(angles), angles[0], math.radians(0.5), 0.05, SCANNER_RANGE)
    readings = resample_scan(scan, ScanMount(), 0.0, WALL_TASK)
    expected = expected_readings(WALL_TASK, both_walls=True)
    assert expected[13] == pytest.approx(1.0 / math.cos(math.radians(50.0)) - 0.2, abs=1e-12)  # 130 deg: covered
    assert expected[14] == pytest.approx(1.0 / math.cos(math.radians(40.0)) - 0.2, abs=1e-12)  # 140 deg: not
    expected[14:23] = WALL_TASK.lidar_range  # 140 ... 220 deg: outside the scanner's -135 ... 135 deg
    np.testing.assert_allclose(readings, expected, rtol=0, atol=1e-12)
    full = beam_angles(-180.0, 0.5, 720)  # the same walls seen all round: the rays behind see the wall x = -1 m
    scan = Scan(corridor_ranges(full), -math.pi, math.radians(0.5), 0.05, SCANNER_RANGE)
    around = resample_scan(scan, ScanMount(), 0.0, WALL_TASK)
    np.testing.assert_allclose(around, expected_readings(WALL_TASK, both_walls=True), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("robot_yaw_deg", "mount_yaw_deg"), [(90.0, 0.0), (0.0, 90.0), (45.0, 45.0)], ids=["odometry", "mount", "both"]
)
def test_rotated_scanner_frame(robot_yaw_deg: float, mount_yaw_deg: float) -> None:
    """The wall x = 1 m seen by a 1 deg scanner whose frame is turned by +90 deg (the robot's heading, the mount's yaw,
    or half of each): its beam k looks along world angle k + 90 deg, so its ranges are the unturned scanner's rolled
    by 90 beams; the readings are the unturned ones."""
    world = beam_angles(0.0, 1.0, 360)
    turned = np.roll(wall_ranges(world), -90)
    scan = Scan(turned, 0.0, math.radians(1.0), 0.05, SCANNER_RANGE)
    mount = ScanMount(yaw=math.radians(mount_yaw_deg))
    readings = resample_scan(scan, mount, math.radians(robot_yaw_deg), WALL_TASK)
    np.testing.assert_allclose(readings, expected_readings(WALL_TASK), rtol=0, atol=1e-12)


def test_clockwise_scanner() -> None:
    """A scanner turning clockwise (negative angle_increment): beam k looks along -k deg, so its ranges are the
    anti-clockwise scanner's in reverse order after the first; the readings are the same."""
    world = beam_angles(0.0, 1.0, 360)
    clockwise = wall_ranges(world)[(-np.arange(360)) % 360]
    scan = Scan(clockwise, 0.0, -math.radians(1.0), 0.05, SCANNER_RANGE)
    np.testing.assert_allclose(resample_scan(scan, ScanMount(), 0.0, WALL_TASK), expected_readings(WALL_TASK), atol=1e-12)
    offset = beam_angles(179.75, -0.7, 514)  # clockwise, no beam along a ray: the segments still lie on the wall
    scan = Scan(wall_ranges(offset), offset[0], -math.radians(0.7), 0.05, SCANNER_RANGE)
    np.testing.assert_allclose(resample_scan(scan, ScanMount(), 0.0, WALL_TASK), expected_readings(WALL_TASK), atol=1e-12)


@pytest.mark.parametrize(("robot_yaw_deg", "increment_deg", "count"), [(0.0, 1.0, 360), (0.0, 0.7, 514), (90.0, 1.0, 360)])
def test_scanner_ahead_of_the_centre(robot_yaw_deg: float, increment_deg: float, count: int) -> None:
    """A scanner 0.1 m ahead of the robot's centre sees the wall x = 1 m at 0.9 / cos(phi) along its beam phi (robot
    facing +x). Its returns lie on the wall, so the segments joining neighbouring returns do too, and every ray from
    the centre meets them where it meets the wall: the readings are the centred scanner's, exactly (a flat wall makes
    the interpolation exact; off the centre no beam is taken as a ray itself). Turned by 90 deg
    (robot heading +y, scanner at (0, 0.1) m), the same wall is seen at beam phi at world angle phi + 90 deg:
    ranges 1 / cos(phi + 90 deg)."""
    yaw = math.radians(robot_yaw_deg)
    angles = beam_angles(0.0, increment_deg, count)
    scanner = np.array([0.1 * math.cos(yaw), 0.1 * math.sin(yaw)])  # the scanner's origin in the world frame
    ranges = wall_ranges(angles + yaw, origin_x=scanner[0])
    scan = Scan(ranges, 0.0, math.radians(increment_deg), 0.05, SCANNER_RANGE)
    readings = resample_scan(scan, ScanMount(0.1, 0.0, 0.0), yaw, WALL_TASK)
    np.testing.assert_allclose(readings, expected_readings(WALL_TASK), rtol=0, atol=1e-12)


def test_scan_points_place_returns_round_the_centre() -> None:
    """A scanner 0.1 m ahead of a robot heading +y (90 deg) sits at (0, 0.1) m from the centre; its beam at 90 deg in
    its frame looks along world 180 deg, so a 2 m return lies at (-2, 0.1) m. A beam at 0 deg with a 1 m return lies at
    (0, 1.1) m; beams without a return (inf, below range_min, beyond range_max, nan) give nan rows."""
    scan = Scan(np.array([1.0, 2.0, np.inf, 0.01, 9.0, np.nan]), 0.0, math.pi / 2, 0.05, 5.0)
    points = scan_points(scan, ScanMount(0.1, 0.0, 0.0), math.pi / 2)
    np.testing.assert_allclose(points[:2], [[0.0, 1.1], [-2.0, 0.1]], atol=1e-15)
    assert np.isnan(points[2:]).all()


def test_returns_outside_the_scanners_limits_read_nothing() -> None:
    """Returns that are inf, nan, below range_min or above range_max are no returns: a scan of them reads nothing."""
    ranges = np.tile([np.inf, np.nan, 0.01, 3.5], 90)
    scan = Scan(ranges, 0.0, math.radians(1.0), 0.05, SCANNER_RANGE)
    readings = resample_scan(scan, ScanMount(), 0.0, WALL_TASK)
    np.testing.assert_array_equal(readings, WALL_TASK.lidar_range)


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_ordinary_scan_warns_nothing() -> None:
    """A scan with beams that see nothing (inf) is ordinary input and raises no warning: here the wall x = -1 m, so
    the beam at 0 deg, whose sine is exactly 0, has no return (inf * 0 would be nan, and numpy would warn). Ray k
    reads what ray k + 18 (180 deg round) reads of the wall x = 1 m."""
    angles = beam_angles(0.0, 1.0, 360)
    scan = Scan(wall_ranges(angles - math.pi), 0.0, math.radians(1.0), 0.05, SCANNER_RANGE)
    readings = resample_scan(scan, ScanMount(), 0.0, WALL_TASK)
    np.testing.assert_allclose(readings, np.roll(expected_readings(WALL_TASK), 18), rtol=0, atol=1e-12)


def test_scan_along_the_task_rays_reads_each_range() -> None:
    """A scan of exactly the task's 90 rays as a ``LaserScan`` holds it (float32 ranges, angle_min -pi and
    angle_increment 4 deg in float32, which put the last beams ~1e-6 rad off their rays): every ray reads its range
    minus R_a, to float32 rounding (6e-8 relative), however far apart neighbouring returns lie; no return reads
    nothing; a return inside the robot reads 0."""
    config = FormationConfig.task("ch5-bearing")
    rng = np.random.default_rng(5)
    ranges = rng.uniform(0.25, 1.65, config.lidar_rays)  # along the task's rays, ray k at 4k deg
    ranges[[3, 40]] = np.inf
    ranges[7] = 0.15  # inside R_a = 0.2 m
    first = config.lidar_rays // 2  # the beam at angle_min = -pi looks along ray 45 (180 deg)
    stored = np.roll(ranges, -first).astype(np.float32)
    increment = float(np.float32(2.0 * math.pi / config.lidar_rays))
    scan = Scan(stored, float(np.float32(-math.pi)), increment, 0.1, 10.0)
    readings = resample_scan(scan, ScanMount(), 0.0, config)
    expected = np.clip(ranges - config.agent_radius, 0.0, config.lidar_range)  # ray 7: 0.15 - 0.2 m, clipped to 0
    np.testing.assert_allclose(readings, expected, rtol=0, atol=2e-7)


# The two channels and the observation rows against the simulator's --------------------------------------------


def disc_entries(config: FormationConfig, origin: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Distance (m) from the agent's surface along each task ray to the first of the discs of radius R_a round
    ``centres`` it enters (inf if none): the ray p + t u meets a disc over t = u.(c - p) -+ sqrt((u.(c - p))^2 -
    |c - p|^2 + R_a^2), and the first such t at or beyond R_a counts."""
    theta = np.arange(config.lidar_rays) * (2.0 * math.pi / config.lidar_rays)
    directions = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    radius = config.agent_radius
    entries = np.full(len(theta), np.inf)
    for centre in centres:
        offset = centre - origin
        projection = directions @ offset
        discriminant = projection**2 - offset @ offset + radius**2
        half_chord = np.sqrt(np.maximum(discriminant, 0.0))
        enter, leave = projection - half_chord, projection + half_chord
        met = (discriminant >= 0.0) & (leave >= radius)
        entries = np.minimum(entries, np.where(met, np.maximum(enter, radius), np.inf))
    return entries - radius


def lidar_of(observation: np.ndarray, layout: dict[str, slice]) -> np.ndarray:
    """The observation's two lidar channels, ``(2, n_rays)``."""
    return np.stack([observation[layout[name]] for name in ("lidar_obstacles", "lidar_agents")])


def random_actions(rng: np.random.Generator, n_agents: int) -> np.ndarray:
    """Actions within [-1, 1], a quarter of the entries at the bounds (so that speed clamps and clips act)."""
    actions = rng.uniform(-1.0, 1.0, (n_agents, 2))
    bound = rng.random((n_agents, 2)) < 0.25
    actions[bound] = np.sign(actions[bound])
    return actions


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_split_of_the_merged_scan_gives_the_simulators_channels(seed: int) -> None:
    """Stage 3 of chapter 5 (obstacles in range, teammates about 1.08 m apart), 30 steps of random actions: each
    agent's scan of every body (``merged_scan``, as a ``LaserScan`` stores it: float32 ranges and increment) resampled
    and split gives the simulator's agent channel on every ray, and its obstacle channel on every ray that no teammate
    stops; a ray a teammate stops (the nearest teammate's disc, computed here by hand, lies before any obstacle and
    within range) reads nothing on the obstacle channel."""
    config = STAGE_3
    env = FormationEnv(config)
    observations = np.stack(list(env.reset(seed=seed)[0].values()))
    rows, layout = env.engine.team_rows(env.team), env.observation_layout
    rng = np.random.default_rng(seed)
    increment = float(np.float32(2.0 * math.pi / config.lidar_rays))
    far = config.agent_radius + config.lidar_range
    counts = np.zeros(3, dtype=int)  # rays stopped by a teammate; obstacles seen on free rays; agents seen
    for step in range(30):
        positions = env.engine.latest.positions[rows]
        scans = merged_scan(env.engine.lidars[env.team], positions)
        for agent in range(config.n_agents):
            scan = Scan(scans[agent].astype(np.float32), 0.0, increment, 0.0, far + 1.0)
            readings = resample_scan(scan, ScanMount(), 0.0, config)
            channels = split_scan(readings, config, positions, agent)
            obstacles, agents = lidar_of(observations[agent], layout)
            teammates = disc_entries(config, positions[agent], np.delete(positions, agent, axis=0))
            stopped = (teammates < obstacles * config.lidar_range) & (teammates < config.lidar_range)
            where = f"seed {seed}, step {step}, agent {agent}"
            np.testing.assert_allclose(channels[1], agents, rtol=0, atol=1e-6, err_msg=where)
            np.testing.assert_allclose(channels[0][~stopped], obstacles[~stopped], rtol=0, atol=1e-6, err_msg=where)
            np.testing.assert_array_equal(channels[0][stopped], 1.0, err_msg=where)
            counts += [stopped.sum(), (obstacles[~stopped] < 1.0).sum(), (agents < 1.0).sum()]
        observations = env.step_array(random_actions(rng, config.n_agents))[0]
    assert (counts > 0).all(), counts  # every case occurred


def test_split_scan_tells_teammates_from_obstacles_by_hand() -> None:
    """Agent 0 at (5, 5), its non-neighbour agent 3 at (6, 5), the rest parked far away: along ray 0 agent 3's disc
    begins 1 - 0.2 - 0.2 = 0.6 m from agent 0's surface (agent channel 0.6 / 1.5 = 0.4). A return at 0.56 m lies
    within the 0.05 m tolerance of it: a teammate, the obstacle channel reads nothing; a return at 0.54 m is 0.06 m
    short of it: an obstacle, 0.54 / 1.5 = 0.36. Agent 3's disc also spans the rays at +-4 and +-8 deg (its half-width
    is asin 0.2 = 11.5 deg): cos 4 - sqrt(0.04 - sin^2 4) - 0.2 = 0.610123 m, cos 8 - sqrt(0.04 - sin^2 8) - 0.2 =
    0.646633 m. With a ring neighbour (agent 1) at (6, 5) instead, the agent channel does not see it, and its return
    is still no obstacle."""
    config = STAGE_3
    parked = [[12.0, 8.0], [12.0, 2.0], [9.0, 8.0], [9.0, 2.0]]
    positions = np.array([[5.0, 5.0], parked[0], parked[1], [6.0, 5.0], parked[2], parked[3]])
    readings = np.full(config.lidar_rays, config.lidar_range)
    readings[0] = 0.56
    channels = split_scan(readings, config, positions, 0)
    seen = [0, 1, 2, 88, 89]  # rays at 0, 4, 8, -8, -4 deg
    expected = np.array([0.6, 0.610123, 0.646633, 0.646633, 0.610123]) / 1.5
    np.testing.assert_allclose(channels[1, seen], expected, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.delete(channels[1], seen), 1.0)
    np.testing.assert_array_equal(channels[0], 1.0)
    readings[0] = 0.54
    channels = split_scan(readings, config, positions, 0)
    assert channels[0, 0] == pytest.approx(0.36, abs=1e-12)
    np.testing.assert_array_equal(channels[0, 1:], 1.0)
    neighbour = positions[[0, 3, 2, 1, 4, 5]]  # agents 1 and 3 swap places
    readings[0] = 0.6
    channels = split_scan(readings, config, neighbour, 0)
    np.testing.assert_array_equal(channels, 1.0)


def contact_scenario() -> Scenario:
    """A hexagon of circumradius 1.08 m round (7.5, 5) with agent 0 (at (8.58, 5), heading +x) 0.03 m from an
    obstacle straight ahead, and agent 2 moved to 0.42 m from agent 3, the two facing each other: pushed on, they
    give the collision term both its obstacle (r_o) and its agent (r_j) values."""
    angles = np.radians(np.arange(6) * 60.0)
    positions = np.array([7.5, 5.0]) + 1.08 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    positions[2] = positions[3] + 0.42 * np.array([math.cos(math.pi / 3), math.sin(math.pi / 3)])
    obstacle = [positions[0, 0] + 0.2 + 0.03 + 0.5, 5.0, 0.5]
    headings = np.radians([0.0, 90.0, 240.0, 60.0, 270.0, 300.0])
    return Scenario(positions, np.array([3.0, 5.0]), np.array([obstacle]), headings=headings)


def contact_actions(rng: np.random.Generator, config: FormationConfig) -> np.ndarray:
    """Agent 0 drives into its obstacle, agents 2 and 3 into each other (a holonomic force along the line joining
    them, or a unicycle's full forward action), the others at random."""
    actions = random_actions(rng, config.n_agents)
    if config.dynamics == "unicycle":
        actions[[0, 2, 3]] = [1.0, 0.0]
    else:
        actions[0] = [1.0, 0.0]
        actions[2] = [-math.cos(math.pi / 3), -math.sin(math.pi / 3)]
        actions[3] = -actions[2]
    return actions


@pytest.mark.parametrize("config", [STAGE_3, UNICYCLE_STAGE_3], ids=["holonomic", "unicycle"])
@pytest.mark.parametrize("placement", ["seed", "contacts"])
def test_observer_reproduces_the_simulators_rows(config: FormationConfig, placement: str) -> None:
    """Each agent's observer, given its team's poses, velocities and headings, the goal and the simulator's lidar
    channels, and told each action it took, writes the simulator's observation row over 40 steps (time_step counting
    0 ... 40, previous_reward the step's reward, its collision term included in the hand-placed contacts); after
    reset() it writes the first row of a new episode again. Every field matches within 1e-9 plus the observation's
    float32 rounding (2^-24 of a value); the previous action and reward match the engine's float64 ones within 1e-9."""
    env = FormationEnv(config)
    rows, layout = env.engine.team_rows(env.team), env.observation_layout
    observers = [AgentObserver(config, agent) for agent in range(config.n_agents)]
    assert observers[0].layout == layout
    rng = np.random.default_rng(7)

    def play(steps: int, options: dict[str, Scenario] | None) -> tuple[np.ndarray, np.ndarray]:
        """Reset the env, run ``steps`` steps comparing every row; return the previous rewards observed, ``(steps + 1,
        n)``, and every step's collision terms, ``(steps, n)``."""
        observations = np.stack(list(env.reset(seed=3, options=options)[0].values()))
        rewards, collisions = [], []
        for step in range(steps + 1):
            engine = env.engine
            headings = engine.dynamics.headings_of(rows)
            team = TeamView(
                engine.latest.positions[rows].copy(),
                engine.latest.velocities[rows].copy(),
                np.zeros(config.n_agents) if headings is None else headings.copy(),
            )
            lidar = engine.episodes.lidar[:, rows]  # the channels the env wrote into its observations, in float64
            for agent, observer in enumerate(observers):
                row = observer.observe(team, lidar[:, agent], env.goal)
                for name, where in layout.items():
                    message = f"{name} of agent {agent} at step {step}"
                    np.testing.assert_allclose(row[where], observations[agent, where], rtol=2**-24, atol=1e-9, err_msg=message)
                assert observer.previous_reward == pytest.approx(engine.episodes.previous_rewards[rows][agent], abs=1e-9)
                np.testing.assert_allclose(observer.previous_action, engine.episodes.previous_actions[rows][agent], atol=1e-9)
            assert observations[0, layout["time_step"]] == step
            rewards.append(observations[:, layout["previous_reward"]].ravel())
            if step == steps:
                break
            actions = contact_actions(rng, config) if options else random_actions(rng, config.n_agents)
            observations, _, terminated, truncated, infos = env.step_array(actions)
            assert not (terminated or truncated)
            collisions.append([info["reward_coll"] for info in infos])
            for agent, observer in enumerate(observers):
                observer.remember(actions[agent])
        return np.array(rewards), np.array(collisions)

    options = {"scenario": contact_scenario()} if placement == "contacts" else None
    rewards, collisions = play(40, options)
    assert np.unique(rewards[1:]).size == rewards[1:].size  # every agent's reward differs at every step
    if placement == "contacts":  # agent 0 stays within d_safe of its obstacle, agents 2 and 3 touch from step 2
        np.testing.assert_array_equal(collisions[:, 0], config.r_o)
        np.testing.assert_array_equal(collisions[1:, [2, 3]], config.r_j)
    else:
        np.testing.assert_array_equal(collisions, 0.0)
    for observer in observers:
        observer.reset()
        assert observer.step == 0
    play(2, options)  # a new episode: step 0 again, no previous action or reward


def test_observer_refuses_a_team_reward_and_an_unknown_agent() -> None:
    """A team reward needs every teammate's obstacle gap; agent indices run 0 ... n - 1."""
    with pytest.raises(ValueError, match="team reward"):
        AgentObserver(FormationConfig.task("ch4-team"), 0)
    for agent in (-1, STAGE_3.n_agents):
        with pytest.raises(ValueError, match=f"agent index {agent} is outside a team of 6"):
            AgentObserver(STAGE_3, agent)


# Commands ----------------------------------------------------------------------------------------------------------


def test_holonomic_velocity_command_by_hand() -> None:
    """F_max = m v_max / dt, so an action a changes the velocity by 0.05 a m/s. From (0.03, 0): action (0.4, -0.2)
    gives (0.05, -0.01), 0.051 m/s, clamped to 0.05 m/s along it: (0.049029, -0.009806); action (-0.2, 0.4) gives
    (0.02, 0.02) unclamped; action (1, 0) gives (0.08, 0), clamped to (0.05, 0); action (0, 1) gives (0.03, 0.05),
    clamped by 0.05 / sqrt(0.0034) = 0.857493 to (0.025725, 0.042875)."""
    config = STAGE_3
    velocity = np.array([0.03, 0.0])
    cases = {
        (0.4, -0.2): [0.049029, -0.009806],
        (-0.2, 0.4): [0.02, 0.02],
        (1.0, 0.0): [0.05, 0.0],
        (0.0, 1.0): [0.025725, 0.042875],
    }
    for action, expected in cases.items():
        command = dynamics_model(config).command(np.array(action), velocity, 0.0)
        np.testing.assert_allclose(command, expected, rtol=0, atol=1e-6)
    assert math.hypot(*dynamics_model(config).command(np.array([0.0, 1.0]), velocity, 0.0)) == pytest.approx(0.05, abs=1e-15)
    # unclamped commands invert exactly; a command out of reach asks for the bounding action
    np.testing.assert_allclose(dynamics_model(config).action(np.array([0.02, 0.02]), velocity, 0.0), [-0.2, 0.4], atol=1e-12)
    np.testing.assert_array_equal(dynamics_model(config).action(np.array([1.0, -1.0]), velocity, 0.0), [1.0, -1.0])


def test_unicycle_velocity_command_by_hand() -> None:
    """Forward speed v_f + 0.05 a_0 clipped to +-0.05 m/s, turn rate 0.5 a_1 rad/s: from 0.04 m/s, (1, -0.5) gives
    (0.05, -0.25) (clipped); (-0.4, 1) gives (0.02, 0.5); from -0.03 m/s, (-1, 0) gives (-0.05, 0) (clipped). The
    velocity does not matter."""
    config = UNICYCLE_STAGE_3
    anything = np.array([9.0, -9.0])
    np.testing.assert_allclose(
        dynamics_model(config).command(np.array([1.0, -0.5]), anything, 0.04), [0.05, -0.25], atol=1e-15
    )
    np.testing.assert_allclose(dynamics_model(config).command(np.array([-0.4, 1.0]), anything, 0.04), [0.02, 0.5], atol=1e-15)
    np.testing.assert_allclose(
        dynamics_model(config).command(np.array([-1.0, 0.0]), anything, -0.03), [-0.05, 0.0], atol=1e-15
    )
    np.testing.assert_allclose(dynamics_model(config).action(np.array([0.02, 0.5]), anything, 0.04), [-0.4, 1.0], atol=1e-12)
    np.testing.assert_array_equal(dynamics_model(config).action(np.array([0.2, -2.0]), anything, 0.0), [1.0, -1.0])


@pytest.mark.parametrize("config", [STAGE_3, UNICYCLE_STAGE_3], ids=["holonomic", "unicycle"])
def test_action_through_its_command_moves_agents_alike(config: FormationConfig) -> None:
    """Two copies of an episode, one stepped with actions a, one with action(command(a)) of the task's dynamics model (what the
    simulator node applies of the command an agent node sends): their agents follow the same paths, within 1e-12 m,
    over 30 steps whose actions are often at the bounds (the speed clamp and the forward clip act). An action whose
    command stays within v_max (|v + 0.05 a| for a point, |v_f + 0.05 a_0| for a unicycle) comes back unchanged."""
    direct, relayed = FormationEnv(config), FormationEnv(config)
    direct.reset(seed=11)
    relayed.reset(seed=11)
    rows = relayed.engine.team_rows(relayed.team)
    rng = np.random.default_rng(11)
    unlimited = []
    for _ in range(30):
        actions = random_actions(rng, config.n_agents)
        engine = relayed.engine
        velocities = engine.latest.velocities[rows].copy()
        speeds = engine.dynamics.forward_speeds_of(rows)
        speeds = np.zeros(config.n_agents) if speeds is None else speeds
        relays = np.array(
            [
                dynamics_model(config).action(dynamics_model(config).command(action, velocity, speed), velocity, speed)
                for action, velocity, speed in zip(actions, velocities, speeds)
            ]
        )
        direct.step_array(actions)
        relayed.step_array(relays)
        np.testing.assert_allclose(relayed.engine.latest.positions, direct.engine.latest.positions, rtol=0, atol=1e-12)
        if config.dynamics == "unicycle":
            within = np.abs(speeds + 0.05 * actions[:, 0]) <= config.v_max
        else:
            within = np.linalg.norm(velocities + 0.05 * actions, axis=1) <= config.v_max
        np.testing.assert_allclose(relays[within], actions[within], rtol=0, atol=1e-12)
        unlimited.extend(within)
    assert 0 < sum(unlimited) < len(unlimited)  # both kinds occurred


# The command that starts the nodes, and the launch file -----------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
SHIPPED_MODEL = ROOT / "src" / "sb3_formation" / "pretrained" / "ch5-bearing" / "final_model.onnx"


def run_module(*arguments: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "sb3_formation.ros", *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, cwd=cwd)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["sim", "missing.onnx"], "no exported policy at missing.onnx"),
        (["sim", str(SHIPPED_MODEL), "--stage", "4"], "--stage 4 is not a curriculum stage"),
        (["sim", str(SHIPPED_MODEL), "--episodes", "0"], "--episodes must be at least 1"),
        (["sim", str(SHIPPED_MODEL), "--rate", "0"], "--rate and --command-timeout must be > 0"),
        (["sim", str(SHIPPED_MODEL), "--out", "episodes.json"], "the episodes are written as an .npz file"),
        (["sim", str(SHIPPED_MODEL), "--out", "taken.npz"], "taken.npz exists"),
        (["agents", str(SHIPPED_MODEL), "--domain-id", "300"], "--domain-id 300 is not a ROS 2 domain id"),
        (["agents", str(SHIPPED_MODEL), "--agents", "0,6"], "--agents 0,6: indices must be distinct and within 0-5"),
        (["sim", str(SHIPPED_MODEL), "--seed", str(2**64)], "--seed: must be an integer in [0, 4,294,967,295]"),
        (["sim", str(SHIPPED_MODEL), "--episodes", str(10**20)], "--episodes: must be an integer in [0, 100,000]"),
        (["sim", str(SHIPPED_MODEL), "--rate", "1e-300"], "--rate 1e-300 is below 0.001"),
        (["sim", str(SHIPPED_MODEL), "--rate", "nan"], "--rate: must be a number in [0, 1000]"),
        (["sim", str(SHIPPED_MODEL), "--command-timeout", "1e309"], "--command-timeout: must be a number in [0, 86400]"),
        (["sim", str(SHIPPED_MODEL), "--out", ""], "--out: the path is empty"),
    ],
)
def test_bad_options_get_one_line_before_anything_starts(arguments: list[str], message: str, tmp_path: Path) -> None:
    (tmp_path / "taken.npz").write_bytes(b"kept")
    done = run_module(*arguments, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and message in done.stderr, done.stderr
    assert (tmp_path / "taken.npz").read_bytes() == b"kept"


def test_an_unknown_option_is_refused() -> None:
    done = run_module("agents", str(SHIPPED_MODEL), "--frobnicate")
    assert done.returncode == 2 and "unrecognized arguments: --frobnicate" in done.stderr


def test_the_cli_refuses_a_target_that_is_not_exported(tmp_path: Path) -> None:
    """``sb3-formation ros`` runs exported policies: a run folder is refused with the command that exports it."""
    done = subprocess.run(
        [sys.executable, "-m", "sb3_formation.cli", "ros", "agents", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and f"export {tmp_path} first" in done.stderr, done.stderr


def test_the_launch_files_commands_are_the_modules() -> None:
    """Each process of ``launch/formation.launch.xml`` is ``python3 -m sb3_formation.ros ...`` with options the module
    accepts, once the launch arguments take their defaults (and the model a path)."""
    launch = ElementTree.parse(ROOT / "launch" / "formation.launch.xml").getroot()
    defaults = {arg.get("name"): arg.get("default", "model.onnx") for arg in launch.iter("arg")}
    commands = [executable.get("cmd", "") for executable in launch.iter("executable")]
    assert len(commands) == 2
    parser = build_parser()
    for command in commands:
        words = shlex.split(re.sub(r"\$\(var (\w+)\)", lambda match: defaults[match.group(1)] or "''", command))
        assert words[:3] == ["python3", "-m", "sb3_formation.ros"]
        parser.parse_args(words[3:])  # exits on an option the module does not know


def test_a_process_per_agent_that_does_not_stop_is_killed_and_shows_where_it_hung() -> None:
    """The parent of ``--process-per-agent``, stopped with SIGTERM, SIGTERMs its children; one that ignores it (a hung
    shutdown) prints its threads' stacks and is killed ``stop_timeout`` s later, and the parent says so and returns 1.
    The other child, which ends on SIGTERM, is not reported."""
    stuck = (
        "import signal, time\n"
        "from sb3_formation.ros.launch import _stop_on_signals\n"
        "_stop_on_signals()\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "def hung_in_shutdown():\n"
        "    print('ready', flush=True)\n"
        "    time.sleep(600)\n"
        "hung_in_shutdown()\n"
    )
    ending = "import time\nprint('ready', flush=True)\ntime.sleep(600)\n"
    parent = (
        "import sys\n"
        "from sb3_formation.ros.launch import _run_children\n"
        f"sys.exit(_run_children([[sys.executable, '-c', {ending!r}], [sys.executable, '-c', {stuck!r}]], 2.0))\n"
    )
    process = subprocess.Popen(
        [sys.executable, "-c", parent], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    try:
        output, ready = process.stdout, []
        assert output is not None
        reader = threading.Thread(target=lambda: ready.extend(output.readline() for _ in range(2)), daemon=True)
        reader.start()
        reader.join(timeout=120)  # a hang guard: both children print at once
        assert ready == ["ready\n", "ready\n"], ready
        process.send_signal(signal.SIGTERM)
        log = process.communicate(timeout=120)[0]  # a hang guard: the parent ends about 3 s after SIGTERM
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 1, log
    assert "in hung_in_shutdown" in log, log  # the stuck child's stack, from SIGUSR1
    reports = log.split("killed `")[1:]  # one per killed child, its command first
    assert len(reports) == 1 and "hung_in_shutdown" in reports[0], log
    assert reports[0].rstrip().endswith("`: it had not ended 2 s after SIGTERM"), log


@pytest.mark.parametrize("where", ["read-only folder", "file as folder"])
def test_an_out_that_cannot_be_written_is_refused_before_anything_is_flown(where: str, tmp_path: Path) -> None:
    """``ros sim --out`` into a folder it cannot write (once found after every episode was flown) is a one-line error
    before the simulator starts: here, where rclpy is not even installed, it is the error given."""
    if where == "file as folder":
        out = tmp_path / "a-file" / "episodes.npz"
        (tmp_path / "a-file").write_text("")
    elif os.geteuid() == 0:  # root writes into any folder but /proc's
        out = Path("/proc/sb3-formation-episodes.npz")
    else:
        folder = tmp_path / "read-only"
        folder.mkdir(mode=0o555)
        out = folder / "episodes.npz"
    done = run_module("sim", str(SHIPPED_MODEL), "--out", str(out))
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and f"--out {out}: cannot write there" in done.stderr, done.stderr
    assert not out.exists()
