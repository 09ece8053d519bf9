"""Moving obstacles: circles that follow waypoints, bounce off the world's border, or walk as the pedestrians of a
crowd model.

A :class:`Mover` is part of a scenario (data, like a static obstacle); :class:`MovingObstacles` moves one episode's
movers ahead of the physics, one environment step at a time: at the start of a step it says where each mover is and
the velocity that takes it, in a straight line, to where it is at the end of the step. The world moves them as
kinematic Pymunk bodies with that velocity (they push agents and are never pushed), the lidar sees them on its
obstacle channel as any obstacle, and their velocities are not observed.

- ``"path"``: along the closed polyline of its waypoints (the last back to the first) at a constant speed; its
  positions at the steps lie exactly on the polyline (within a step it cuts a corner as a chord).
- ``"bounce"``: from its first waypoint towards its second at a constant speed, mirrored at the world's border
  (its centre stays within ``[r, W - r] x [r, H - r]``); it passes through static obstacles and walls.
- ``"walk"``: a pedestrian of navground's crowd model (its behaviour named by :attr:`Mover.behavior`, ORCA by
  default as in CrowdNav) that walks to its waypoints in turn, over and over, at its preferred speed, avoiding the
  other pedestrians, the static obstacles, the walls and the border. With ``reacts`` it also sees and avoids the
  agents (their positions and velocities at the start of the step); without it, it walks as if they were not there.
  One scenario's walkers either all react or all do not (navground's agents see every other agent in range).

navground (IDSIA's crowd simulator: ORCA, HRVO, HL and social-force behaviours with a C++ core) is used rather than
pyrvo because it offers several behaviours behind one interface, it steps a crowd in C++ in one call, and it needs
only numpy and PyYAML (pyrvo brings a robot simulator with matplotlib, scipy and shapely); the crowd model computes in
single precision, so a walker's positions are float32 values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import navground.core as crowd_core
import navground.sim as crowd_sim
import numpy as np

#: How a mover moves (see the module docstring).
MOTIONS = ("path", "bounce", "walk")
#: navground's behaviours a walker may use.
CROWD_BEHAVIORS = ("ORCA", "HRVO", "HL", "SocialForce")
#: How close (m) a walker comes to a waypoint before it walks to the next.
WAYPOINT_TOLERANCE = 0.25
#: How far (m) a walker sees other walkers, the agents and the static shapes: 20 times what the fastest walker of the
#: families (1.5 v_max, 0.075 m/s) covers in a step of 0.3 s, and more than its ORCA time horizon covers.
CROWD_SENSING_RANGE = 2.0


@dataclass(frozen=True)
class Mover:
    """A moving circular obstacle.

    :param radius: its radius (m)
    :param waypoints: ``(p, 2)`` points (m), ``p >= 2``; it starts at the first
    :param speed: its speed (m/s): constant for ``"path"`` and ``"bounce"``, the preferred and highest speed of a walker
    :param motion: ``"path"``, ``"bounce"`` or ``"walk"`` (see the module docstring)
    :param reacts: a walker sees and avoids the agents (ignored by the other motions)
    :param behavior: a walker's navground behaviour, one of :data:`CROWD_BEHAVIORS`
    """

    radius: float
    waypoints: np.ndarray
    speed: float
    motion: str = "path"
    reacts: bool = False
    behavior: str = "ORCA"

    def __post_init__(self) -> None:
        waypoints = np.array(self.waypoints, dtype=np.float64)
        if waypoints.ndim != 2 or waypoints.shape[1] != 2 or len(waypoints) < 2:
            raise ValueError(f"Mover.waypoints must have shape (p, 2) with p >= 2, got {waypoints.shape}")
        if not np.all(np.isfinite(waypoints)):
            raise ValueError("Mover.waypoints contains NaN or infinite values")
        if self.motion not in MOTIONS:
            raise ValueError(f"Mover.motion={self.motion!r} is invalid: it must be one of {MOTIONS}")
        if self.behavior not in CROWD_BEHAVIORS:
            raise ValueError(f"Mover.behavior={self.behavior!r} is invalid: it must be one of {CROWD_BEHAVIORS}")
        for name in ("radius", "speed"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"Mover.{name}={value} is invalid: it must be a finite number > 0")
        legs = np.roll(waypoints, -1, axis=0) - waypoints
        if self.motion != "walk" and np.any(np.hypot(legs[:, 0], legs[:, 1]) == 0):
            raise ValueError("Mover.waypoints repeats a point: consecutive waypoints (the last and the first too) differ")
        waypoints.setflags(write=False)
        object.__setattr__(self, "waypoints", waypoints)
        object.__setattr__(self, "radius", float(self.radius))
        object.__setattr__(self, "speed", float(self.speed))

    @property
    def start(self) -> np.ndarray:
        """``(2,)`` where it starts (m)."""
        start: np.ndarray = self.waypoints[0]
        return start


@dataclass
class _PathState:
    """Where a ``"path"`` mover is: on the leg from waypoint ``leg`` to the next, ``along`` metres past its start."""

    leg: int = 0
    along: float = 0.0


@dataclass
class MovingObstacles:
    """One episode's movers, moved ahead of the physics one environment step at a time.

    :param movers: the scenario's movers
    :param dt: the environment step (s)
    :param width: the world's width (m)
    :param height: the world's height (m)
    :param obstacles: ``(m, 3)`` the static circles (x, y, radius in m), which walkers avoid
    :param walls: ``(w, 5)`` the walls (x0, y0, x1, y1, thickness in m), which walkers avoid
    :param agent_radius: the agents' radius R_a (m), for walkers that react to them
    """

    movers: tuple[Mover, ...]
    dt: float
    width: float
    height: float
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    walls: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    agent_radius: float = 0.0

    def __post_init__(self) -> None:
        movers = self.movers
        #: ``(k, 2)`` every mover's centre (m) now
        self.positions = np.array([mover.start for mover in movers], dtype=np.float64).reshape(-1, 2)
        #: ``(k, 2)`` the velocity (m/s) of every mover over the last step (0 before the first)
        self.velocities = np.zeros_like(self.positions)
        self.radii = np.array([mover.radius for mover in movers], dtype=np.float64)
        self._paths = {index: _PathState() for index, mover in enumerate(movers) if mover.motion == "path"}
        self._bouncing = {
            index: _unit(mover.waypoints[1] - mover.waypoints[0]) * mover.speed
            for index, mover in enumerate(movers)
            if mover.motion == "bounce"
        }
        walkers = [index for index, mover in enumerate(movers) if mover.motion == "walk"]
        reacting = {movers[index].reacts for index in walkers}
        if len(reacting) > 1:
            raise ValueError("the walkers of one scenario must all react to the agents or all not react")
        self._walkers = np.array(walkers, dtype=np.int64)
        self.reacts = reacting == {True}
        self._crowd: crowd_sim.World | None = None
        self._pedestrians: list[crowd_sim.Agent] = []
        self._robots: list[crowd_sim.Agent] = []  # the agents in the crowd model, for walkers that react to them
        if walkers:
            self._crowd, self._pedestrians = self._crowd_world(walkers)

    @property
    def circles(self) -> np.ndarray:
        """``(k, 3)`` every mover's x, y, radius (m) now (a new array)."""
        return np.column_stack([self.positions, self.radii])

    def step(self, agent_positions: np.ndarray, agent_velocities: np.ndarray) -> np.ndarray:
        """Move every mover over one step: return the velocities (m/s) that take them from :attr:`positions` to their
        positions at the end of the step, which :attr:`positions` then holds.

        :param agent_positions: ``(n, 2)`` the agents' centres (m) at the start of the step (for reacting walkers)
        :param agent_velocities: ``(n, 2)`` the agents' velocities (m/s) then
        :return: ``(k, 2)`` the step's velocities (also in :attr:`velocities`)
        """
        following = self.positions.copy()
        for index, state in self._paths.items():
            following[index] = self._follow(self.movers[index], state)
        for index, velocity in self._bouncing.items():
            following[index], self._bouncing[index] = self._bounce(index, velocity)
        if self._crowd is not None:
            following[self._walkers] = self._walk(agent_positions, agent_velocities)
        self.velocities = (following - self.positions) / self.dt
        self.positions = following
        return self.velocities

    def _follow(self, mover: Mover, state: _PathState) -> np.ndarray:
        """A ``"path"`` mover's position one step on (``state`` advanced)."""
        waypoints, left = mover.waypoints, mover.speed * self.dt
        while True:
            start, end = waypoints[state.leg], waypoints[(state.leg + 1) % len(waypoints)]
            length = math.hypot(*(end - start).tolist())
            if state.along + left < length:
                state.along += left
                position: np.ndarray = start + (end - start) * (state.along / length)
                return position
            left -= length - state.along
            state.leg, state.along = (state.leg + 1) % len(waypoints), 0.0

    def _bounce(self, index: int, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A ``"bounce"`` mover's position one step on, and its velocity after any reflection."""
        radius, position, velocity = self.radii[index], self.positions[index] + velocity * self.dt, velocity.copy()
        for axis, size in ((0, self.width), (1, self.height)):
            low, high = radius, size - radius
            while not low <= position[axis] <= high:  # a step may cross the box more than once only when very fast
                position[axis] = 2 * low - position[axis] if position[axis] < low else 2 * high - position[axis]
                velocity[axis] = -velocity[axis]
        return position, velocity

    def _crowd_world(self, walkers: list[int]) -> tuple[crowd_sim.World, list[crowd_sim.Agent]]:
        """navground's world of the walkers, the static shapes and the border (the agents join at the first step when
        the walkers react to them), and the walkers' agents in it."""
        world = crowd_sim.World()
        world.ignore_collisions = True  # contacts are Pymunk's: the crowd model only chooses the walkers' velocities
        for x, y, radius in self.obstacles.tolist():
            world.add_obstacle(crowd_sim.Obstacle((x, y), radius))
        corners = [(0.0, 0.0), (self.width, 0.0), (self.width, self.height), (0.0, self.height)]
        segments = [(*start, *end) for start, end in zip(corners, corners[1:] + corners[:1])]
        for x0, y0, x1, y1 in segments + [tuple(wall[:4]) for wall in self.walls.tolist()]:
            world.add_wall(crowd_sim.Wall((x0, y0), (x1, y1)))
        pedestrians = []
        for index in walkers:
            mover = self.movers[index]
            behavior = crowd_core.Behavior.make_type(mover.behavior)
            assert behavior is not None  # one of CROWD_BEHAVIORS, which navground registers
            behavior.optimal_speed = mover.speed
            pedestrian = crowd_sim.Agent(
                radius=mover.radius,
                behavior=behavior,
                kinematics=crowd_core.kinematics.OmnidirectionalKinematics(max_speed=mover.speed),
                task=crowd_sim.tasks.WaypointsTask(
                    waypoints=[tuple(point) for point in mover.waypoints[1:].tolist()] + [tuple(mover.start.tolist())],
                    loop=True,
                    tolerance=WAYPOINT_TOLERANCE,
                ),
                state_estimations=[crowd_sim.state_estimations.BoundedStateEstimation(range=CROWD_SENSING_RANGE)],
            )
            pedestrian.position = mover.start
            world.add_agent(pedestrian)
            pedestrians.append(pedestrian)
        return world, pedestrians

    def _walk(self, agent_positions: np.ndarray, agent_velocities: np.ndarray) -> np.ndarray:
        """The walkers' positions one step on: one update of the crowd model (the agents placed in it first when the
        walkers react to them)."""
        world = self._crowd
        assert world is not None  # only called with walkers
        if self.reacts:
            if not self._robots:
                for _ in range(len(agent_positions)):
                    robot = crowd_sim.Agent(
                        radius=self.agent_radius,
                        behavior=crowd_core.behaviors.DummyBehavior(),
                        kinematics=crowd_core.kinematics.OmnidirectionalKinematics(max_speed=0.0),
                    )
                    world.add_agent(robot)
                    self._robots.append(robot)
            for robot, position, velocity in zip(self._robots, agent_positions, agent_velocities):
                robot.position, robot.velocity = position, velocity
        world.update(self.dt)
        return np.array([pedestrian.position for pedestrian in self._pedestrians], dtype=np.float64)


def _unit(vector: np.ndarray) -> np.ndarray:
    """``vector`` scaled to length 1."""
    unit: np.ndarray = vector / math.hypot(*vector.tolist())
    return unit
