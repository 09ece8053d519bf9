"""From a real scanner's ``LaserScan`` to the simulator's two lidar channels, and back (``docs/deployment.md``).

Numpy and the environment layer only (no rclpy): the agent node and the simulator node call these functions on the
arrays of their messages, and the tests call them on hand-made scans.

- :func:`resample_scan` turns a scan of any angular resolution, angle range, frame and mounting point into the task's
  rays: ``n_rays`` rays ``360 / n_rays`` deg apart from +x of the world frame, each reading the distance from the
  agent's surface to the first return along it (the simulator's lidar, :mod:`~sb3_formation.env.sensors`).
- :func:`split_scan` separates agents from obstacles with the known poses of the team, as the observation's two
  channels require (thesis Table 3.1: obstacles and walls; agents other than the ring neighbours).
- :func:`merged_scan` is what a real scanner on an agent of the simulator sees: both channels and the ring neighbours
  in one, each ray stopped by the first body it meets, in metres from the agent's centre (under a heading error, along
  the rays the engine's disturbed lidar casts); :func:`with_beam_errors` adds the engine's range errors and dropped
  beams.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.geometry import flying_ring
from sb3_formation.env.sensors import AGENT_CHANNEL, OBSTACLE_CHANNEL, Lidar, LidarLayout, lidar_ranges, ray_directions

#: Angle (rad) within which a scanner's beam counts as the task's ray itself (its reading is taken as it is): a
#: ``LaserScan`` holds its angles as float32, which places beam 89 of 90 about 1e-6 rad off the ray it was cast along.
ALIGNED_ANGLE = 1e-5


class ScanMount(NamedTuple):
    """Where the scanner sits on the robot: its frame's origin and yaw in the robot's base frame (REP 103: x forward,
    y left, yaw anti-clockwise). A scanner at the robot's centre looking forward is ``ScanMount(0, 0, 0)``."""

    x: float = 0.0  #: (m)
    y: float = 0.0  #: (m)
    yaw: float = 0.0  #: (rad)


class Scan(NamedTuple):
    """The fields of a ``sensor_msgs/LaserScan`` that place its returns (REP 117: ``inf`` means no return in range)."""

    ranges: np.ndarray  #: ``(k,)`` ranges (m) from the scanner's origin; non-finite or outside the limits: no return
    angle_min: float  #: (rad) angle of the first beam in the scanner's frame
    angle_increment: float  #: (rad) between beams (negative for a clockwise scanner)
    range_min: float  #: (m)
    range_max: float  #: (m)


def scan_points(scan: Scan, mount: ScanMount, yaw: float) -> np.ndarray:
    """The returns of ``scan`` as points relative to the robot's centre in the world frame's axes, ``(k, 2)`` m, with
    ``nan`` rows for the beams without one.

    :param yaw: the robot's heading (rad) in the world frame (its odometry's)
    """
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    valid = np.isfinite(ranges) & (ranges >= scan.range_min) & (ranges <= scan.range_max)
    angles = yaw + mount.yaw + scan.angle_min + scan.angle_increment * np.arange(len(ranges))
    cos, sin = math.cos(yaw), math.sin(yaw)
    origin = np.array([cos * mount.x - sin * mount.y, sin * mount.x + cos * mount.y])
    points = origin + np.where(valid, ranges, 0.0)[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    points[~valid] = np.nan
    return points


def resample_scan(scan: Scan, mount: ScanMount, yaw: float, config: FormationConfig, max_gap: float = 0.1) -> np.ndarray:
    """The task's lidar rays read off a scan: ``(n_rays,)`` distances (m) from the agent's surface, in
    [0, ``lidar_range``] (``lidar_range``: nothing seen).

    The rule, for each of the task's rays from the agent's centre (:func:`~sb3_formation.env.sensors.ray_directions`):
    a beam that points along the ray from the centre gives its return; otherwise the ray meets the segments joining
    the returns of neighbouring beams that lie at most ``max_gap`` apart (one surface), and reads the nearest meeting;
    a ray that meets none reads the nearest return whose direction from the centre lies within half the scanner's
    increment of it, else nothing. Parts of the circle the scanner does not cover read nothing.

    :param scan: the scan (any resolution, angle range and direction of rotation)
    :param mount: where the scanner sits on the robot
    :param yaw: the robot's heading (rad) in the world frame
    :param config: the task (its rays, range and R_a)
    :param max_gap: the largest distance (m) between the returns of neighbouring beams taken as one surface
    """
    points = scan_points(scan, mount, yaw)
    directions = ray_directions(config.lidar_rays)
    valid = ~np.isnan(points[:, 0])
    points, reach = points[valid], np.linalg.norm(points[valid], axis=1)
    angles = np.arctan2(points[:, 1], points[:, 0]) - np.arctan2(directions[:, 1], directions[:, 0])[:, None]
    offsets = np.abs(np.arctan2(np.sin(angles), np.cos(angles)))  # (rays, returns): angle (rad) between ray and return
    centred = mount.x == 0.0 and mount.y == 0.0
    aligned = _nearest(reach, offsets <= ALIGNED_ANGLE) if centred else np.full(len(directions), np.inf)
    start, end = points, np.roll(points, -1, axis=0)  # each return and the next (the last and the first)
    joined = np.flatnonzero((np.linalg.norm(end - start, axis=1) <= max_gap) & _neighbouring(valid, scan.angle_increment))
    meetings = _ray_segment_distances(directions, start[joined], end[joined])
    near = _nearest(reach, offsets <= abs(scan.angle_increment) / 2)
    distances = np.where(np.isfinite(aligned), aligned, np.where(np.isfinite(meetings), meetings, near))
    far = config.agent_radius + config.lidar_range
    readings: np.ndarray = np.clip(np.minimum(distances, far) - config.agent_radius, 0.0, config.lidar_range)
    return readings


def _nearest(reach: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """Per ray, the smallest ``reach`` among its ``chosen`` returns (``(rays, returns)`` mask), ``inf`` if none."""
    nearest: np.ndarray = np.where(chosen, reach[None, :], np.inf).min(axis=1, initial=np.inf)
    return nearest


def _neighbouring(valid: np.ndarray, increment: float) -> np.ndarray:
    """For each valid beam and the next valid one (the last and the first), whether they are neighbouring beams: next in
    the scan, or the last and the first of a scan round the full circle."""
    beams = np.flatnonzero(valid)
    neighbouring: np.ndarray = np.roll(beams, -1) - beams == 1
    full_circle = abs(len(valid) * increment) >= 2.0 * math.pi - abs(increment) - 1e-9
    if beams.size > 1:
        neighbouring[-1] = full_circle and beams[-1] == len(valid) - 1 and beams[0] == 0
    return neighbouring


def _ray_segment_distances(directions: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Per ray from the origin along ``directions`` (``(rays, 2)``), the distance (m) to the nearest of the segments
    ``start -> end`` (``(k, 2)`` each) it meets, ``inf`` if none."""
    edge = end - start
    denominator = directions[:, :1] * edge[None, :, 1] - directions[:, 1:] * edge[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        along = (start[:, 0] * edge[:, 1] - start[:, 1] * edge[:, 0])[None, :] / denominator  # along the ray
        where = (start[None, :, 0] * directions[:, 1:] - start[None, :, 1] * directions[:, :1]) / denominator  # 0..1
    hit = (denominator != 0.0) & (along >= 0.0) & (where >= 0.0) & (where <= 1.0)
    distances: np.ndarray = np.where(hit, along, np.inf).min(axis=1, initial=np.inf)
    return distances


def team_layout(
    config: FormationConfig, positions: np.ndarray, agent: int, neighbours_too: bool, flying: np.ndarray | None = None
) -> LidarLayout:
    """The team's flying agents as the lidar's circles, seen by ``agent`` on the agent channel: all but itself, and but
    its ring neighbours (on the ring of the flying agents, :func:`~sb3_formation.env.geometry.flying_ring`) unless
    ``neighbours_too``; a failed teammate is no agent (the simulator's obstacle channel sees it)."""
    n_agents = len(positions)
    flying = np.ones(n_agents, dtype=bool) if flying is None else np.asarray(flying, dtype=bool)
    circles = np.column_stack([positions, np.full(n_agents, config.agent_radius)])
    visible = flying[None].copy()
    visible[0, agent] = False
    if not neighbours_too:
        visible[0, flying_ring(flying).neighbours[agent]] = False
    return LidarLayout(circles, visible, np.full(n_agents, AGENT_CHANNEL), np.zeros((0, 5)))


def teammate_distances(
    config: FormationConfig, positions: np.ndarray, agent: int, neighbours_too: bool, flying: np.ndarray | None = None
) -> np.ndarray:
    """Distances (m) from ``agent``'s surface to its flying teammates along each task ray, as the simulator's agent
    channel computes them (its own ray cast), in [0, ``lidar_range``]; with ``neighbours_too`` the ring neighbours
    count."""
    ranges = np.empty((2, 1, config.lidar_rays))
    origin = np.ascontiguousarray(positions[agent : agent + 1], dtype=np.float64)
    layout = team_layout(config, np.asarray(positions, dtype=np.float64), agent, neighbours_too, flying)
    lidar_ranges(
        origin,
        ray_directions(config.lidar_rays),
        layout,
        config.agent_radius,
        config.world_width,
        config.world_height,
        config.lidar_range,
        ranges,
    )
    return ranges[AGENT_CHANNEL, 0]


def split_scan(
    readings: np.ndarray,
    config: FormationConfig,
    positions: np.ndarray,
    agent: int,
    tolerance: float = 0.05,
    flying: np.ndarray | None = None,
) -> np.ndarray:
    """The observation's two lidar channels, ``(2, n_rays)`` fractions of the range (1: nothing), from the task's rays
    read off a real scan (:func:`resample_scan`) and the team's positions.

    The rule: the agent channel is the simulator's ray cast at the teammates' discs (R_a round each known position),
    all but the agent and its ring neighbours, so it sees a teammate behind an obstacle as the simulator does. A ray's
    return is a teammate's (any teammate's, ring neighbours included) when it lies within ``tolerance`` of where the
    ray meets that teammate's disc; every other return is an obstacle's. A ray stopped by a teammate cannot see what lies
    behind it: its obstacle reading is "nothing" (1), which is the simulator's unless an obstacle stands within range
    behind that teammate.

    :param readings: ``(n_rays,)`` distances (m) from the agent's surface along the task's rays
    :param positions: ``(n, 2)`` the team's positions (m) in the world frame, row ``agent`` the agent's
    :param agent: the agent's index in its team
    :param tolerance: (m) how far a return may lie from a teammate's disc and still be that teammate
    :param flying: ``(n,)`` bool: the teammates that fly (``None``: every one); a failed one's returns are an
        obstacle's, and the ring neighbours are those of the flying agents' ring
    """
    teammates = teammate_distances(config, positions, agent, neighbours_too=True, flying=flying)
    readings = np.asarray(readings, dtype=np.float64)
    seen = readings < config.lidar_range
    by_teammate = seen & (teammates < config.lidar_range) & (np.abs(readings - teammates) <= tolerance)
    obstacles = np.where(seen & ~by_teammate, readings, config.lidar_range)
    agents = teammate_distances(config, positions, agent, neighbours_too=False, flying=flying)
    channels: np.ndarray = np.stack([obstacles, agents]) / config.lidar_range
    return channels


def merged_scan(
    lidar: Lidar, positions: np.ndarray, stopped_by_agents: bool = True, heading_errors: np.ndarray | None = None
) -> np.ndarray:
    """What a real scanner at each agent's centre sees in the simulator: every body (obstacles, walls, the world's
    border, every other agent) stops a ray; ``(n, n_rays)`` ranges (m) from the agent's centre, ``inf`` where nothing
    lies within the lidar's range (REP 117).

    :param lidar: the team's lidar (its obstacles, walls and directions)
    :param positions: ``(n, 2)`` the agents' centres (m)
    :param stopped_by_agents: the other agents stop rays; ``False``: the scan sees through them, as the simulator's
        obstacle channel does (but for an agent that failed: an obstacle there)
    :param heading_errors: ``(n,)`` each agent's heading error (rad): its beam k looks along the lidar's direction k
        turned by minus its error, as the engine's disturbed lidar does (the agent reads it in the frame of its heading
        estimate); ``None``: along the lidar's directions
    """
    n_agents = len(positions)
    circles, visible, channels, walls = lidar.layout
    circles = circles.copy()
    circles[-n_agents:, :2] = positions
    everyone = np.ones_like(visible)
    failed = channels[-n_agents:] == OBSTACLE_CHANNEL  # an agent that failed is an obstacle, seen through or not
    everyone[:, -n_agents:] = ~np.eye(n_agents, dtype=bool) & (stopped_by_agents | failed)
    obstacle_channels = np.full(len(channels), OBSTACLE_CHANNEL)
    ranges = np.empty((2, n_agents, len(lidar.directions)))
    origins = np.ascontiguousarray(positions, dtype=np.float64)
    geometry = (lidar.agent_radius, lidar.width, lidar.height, lidar.max_range)
    if heading_errors is None:
        lidar_ranges(origins, lidar.directions, LidarLayout(circles, everyone, obstacle_channels, walls), *geometry, ranges)
    else:
        for agent, error in enumerate(np.asarray(heading_errors, dtype=np.float64).tolist()):
            own = LidarLayout(circles, np.ascontiguousarray(everyone[agent : agent + 1]), obstacle_channels, walls)
            out = np.empty((2, 1, len(lidar.directions)))
            lidar_ranges(origins[agent : agent + 1], turned_directions(lidar.directions, -error), own, *geometry, out)
            ranges[:, agent] = out[:, 0]
    readings = ranges[OBSTACLE_CHANNEL]
    return np.where(readings < lidar.max_range, readings + lidar.agent_radius, np.inf)


def turned_directions(directions: np.ndarray, angle: float) -> np.ndarray:
    """``(n_rays, 2)`` unit directions turned anti-clockwise by ``angle`` (rad)."""
    cos, sin = math.cos(angle), math.sin(angle)
    x, y = directions[:, 0], directions[:, 1]
    return np.ascontiguousarray(np.stack([cos * x - sin * y, sin * x + cos * y], axis=1))


def with_beam_errors(
    ranges: np.ndarray, beam_noise: np.ndarray, dropped: np.ndarray, agent_radius: float, lidar_range: float
) -> np.ndarray:
    """Scans (:func:`merged_scan`'s ``(n, n_rays)`` ranges, m from the centre) with the engine's lidar errors
    (:class:`~sb3_formation.env.disturbed.SensedTeams`): a return's distance from the agent's surface plus its beam's
    error (a share of ``lidar_range``), clipped to [0, ``lidar_range``]; a dropped beam returns nothing (``inf``).
    Empty arrays: no such error.

    :param beam_noise: ``(n, n_rays)`` each beam's range error as a share of ``lidar_range``, or empty
    :param dropped: ``(n, n_rays)`` bool: the beam returned nothing, or empty
    """
    ranges = np.array(ranges, dtype=np.float64)
    seen = np.isfinite(ranges)
    if np.size(beam_noise):
        reach = np.clip(np.where(seen, ranges, agent_radius) - agent_radius + beam_noise * lidar_range, 0.0, lidar_range)
        ranges = np.where(seen, reach + agent_radius, np.inf)
    if np.size(dropped):
        ranges[np.asarray(dropped, dtype=bool)] = np.inf
    return ranges
