"""The Pymunk world: the only stateful physics object. Forces in, positions and velocities out.

Agents are dynamic circles that do not rotate; obstacles are static circles; the world's border is four thick static
walls. Each environment step applies the agents' forces as the second-order integrator of eq. 19 (semi-implicit
Euler, as Pymunk itself integrates): v <- v + F / m * dt, then the speed is clamped to v_max, then Pymunk moves the
bodies over ``config.physics_substeps`` sub-steps and resolves contacts (inelastic, frictionless). Contacts are counted
once per pair per environment step.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pymunk
import pymunk.batch
from pymunk._chipmunk import lib as chipmunk

from sb3_formation.env.config import COLLISION_BIAS, FormationConfig
from sb3_formation.env.scenarios import Scenario

AGENT_COLLISION_TYPE = 1
OBSTACLE_COLLISION_TYPE = 2  #: obstacles and walls
WALL_THICKNESS = 1.0  #: m; the walls' inner faces lie exactly on the world's border
COLLISION_SLOP = 1e-3  #: m; Pymunk's allowed overlap (its default 0.1 is for pixel units)
_STATE_FIELDS = pymunk.batch.BodyFields.POSITION | pymunk.batch.BodyFields.VELOCITY
_VELOCITY_FIELD = pymunk.batch.BodyFields.VELOCITY


@numba.njit(cache=True)
def clamp_speed(velocities: np.ndarray, v_max: float) -> np.ndarray:  # pragma: no cover - compiled
    """Scale down every velocity faster than ``v_max`` (m/s) to ``v_max``, keeping its direction.

    :param velocities: ``(n, 2)`` velocities (m/s)
    :param v_max: speed limit (m/s)
    :return: a new ``(n, 2)`` array
    """
    clamped = velocities.copy()
    for index in range(velocities.shape[0]):
        speed = math.hypot(velocities[index, 0], velocities[index, 1])
        if speed > v_max:
            clamped[index] *= v_max / speed
    return clamped


@numba.njit(cache=True)
def split_state(state: np.ndarray, v_max: float) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Positions and velocities from Pymunk's ``(n, 4)`` rows (x, y, v_x, v_y), the velocities clamped to ``v_max``:
    contacts never add speed beyond numerical noise, but the bound is a promise, so what Pymunk returns is clamped too.

    :return: two new ``(n, 2)`` arrays (m, m/s)
    """
    positions, velocities = np.empty((state.shape[0], 2)), np.empty((state.shape[0], 2))
    for index in range(state.shape[0]):
        positions[index, 0], positions[index, 1] = state[index, 0], state[index, 1]
        velocities[index, 0], velocities[index, 1] = state[index, 2], state[index, 3]
    return positions, clamp_speed(velocities, v_max)


class World:
    """One team's Pymunk space, built from a :class:`Scenario`; :meth:`place` puts the next episode's in the same space.

    :param config: task configuration (world size, agent radius and mass, v_max, dt, sub-steps)
    :param scenario: placement of agents, goal and obstacles (validated by the caller)
    """

    def __init__(self, config: FormationConfig, scenario: Scenario) -> None:
        self.config = config
        self.space = pymunk.Space()
        self.space.collision_slop = COLLISION_SLOP
        self.space.collision_bias = COLLISION_BIAS  # the substeps of the config are chosen for it
        self.space.iterations = 20  # keeps a column of 16 agents pressed on a wall within 1 cm
        self._agent_pairs: set[tuple[int, int]] = set()
        self._obstacle_pairs: set[tuple[int, int]] = set()
        self.space.on_collision(AGENT_COLLISION_TYPE, AGENT_COLLISION_TYPE, pre_solve=self._record_agent_contact)
        self.space.on_collision(AGENT_COLLISION_TYPE, OBSTACLE_COLLISION_TYPE, pre_solve=self._record_obstacle_contact)
        # Pymunk's batch API reads and writes every body of the space at once, in the space's own order
        self._read_buffer = pymunk.batch.Buffer()
        self._write_buffer = pymunk.batch.Buffer()
        self._substep = config.dt / config.physics_substeps
        self.place(scenario)

    def place(self, scenario: Scenario) -> None:
        """Empty the space and put the walls, the obstacles and the agents of ``scenario`` in it, as a new world would.

        Reusing one space for every episode keeps memory flat: a Pymunk space is freed only by Python's cyclic
        garbage collector, which lets thousands of old ones wait.

        :param scenario: placement of agents, goal and obstacles (validated by the caller)
        """
        config = self.config
        self.space.remove(*self.space.shapes, *self.space.bodies)
        # the walls and obstacles hang on a static body of this episode (the space's own would keep every old shape)
        self._static_body = pymunk.Body(body_type=pymunk.Body.STATIC)
        self.space.add(self._static_body)
        self.agent_bodies: list[pymunk.Body] = []
        self._agent_of_shape: dict[pymunk.Shape, int] = {}
        self._obstacle_of_shape: dict[pymunk.Shape, int] = {}
        self._add_walls()
        for x, y, radius in scenario.obstacles:
            shape = pymunk.Circle(self._static_body, float(radius), (float(x), float(y)))
            self._add_obstacle_shape(shape)
        for index, (x, y) in enumerate(scenario.agent_positions):
            body = pymunk.Body(config.agent_mass, float("inf"))
            body.position = (float(x), float(y))
            shape = pymunk.Circle(body, config.agent_radius)
            shape.collision_type = AGENT_COLLISION_TYPE
            self.space.add(body, shape)
            self.agent_bodies.append(body)
            self._agent_of_shape[shape] = index
        self._read_buffer.clear()
        pymunk.batch.get_space_bodies(self.space, pymunk.batch.BodyFields.BODY_ID, self._read_buffer)
        body_ids = list(np.frombuffer(self._read_buffer.int_buf(), dtype=np.uintp))
        rows = [body_ids.index(body.id) for body in self.agent_bodies]
        contiguous = rows == list(range(rows[0], rows[0] + len(rows)))
        self._agent_rows = slice(rows[0], rows[0] + len(rows)) if contiguous else np.array(rows)
        self._body_velocities = np.zeros((len(body_ids), 2))  # static bodies keep velocity 0
        self._write_buffer.clear()
        self._write_buffer.set_float_buf(self._body_velocities.ravel())  # Pymunk reads this array's memory
        # Space.step's Python bookkeeping (new bodies' checks, removed shapes) runs here, once per episode: a step of 0 s
        # does only that (Chipmunk returns at once), and move() then calls Chipmunk's step directly
        self.space.step(0.0)
        self.positions = np.array(scenario.agent_positions, dtype=np.float64)
        self.velocities = np.zeros_like(self.positions)

    def _add_walls(self) -> None:
        width, height, half = self.config.world_width, self.config.world_height, WALL_THICKNESS / 2
        corners = [(-half, -half), (width + half, -half), (width + half, height + half), (-half, height + half)]
        for start, end in zip(corners, corners[1:] + corners[:1]):
            self._add_obstacle_shape(pymunk.Segment(self._static_body, start, end, half))

    def _add_obstacle_shape(self, shape: pymunk.Shape) -> None:
        shape.collision_type = OBSTACLE_COLLISION_TYPE
        self._obstacle_of_shape[shape] = len(self._obstacle_of_shape)
        self.space.add(shape)

    def _record_agent_contact(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        first, second = (self._agent_of_shape[shape] for shape in arbiter.shapes)
        self._agent_pairs.add((min(first, second), max(first, second)))

    def _record_obstacle_contact(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        agent_shape, obstacle_shape = arbiter.shapes
        self._obstacle_pairs.add((self._agent_of_shape[agent_shape], self._obstacle_of_shape[obstacle_shape]))

    def step(self, forces: np.ndarray) -> tuple[list[int], list[int]]:
        """Advance one environment step of ``config.dt`` seconds under ``forces``.

        :param forces: ``(n, 2)`` forces (N), held over the step
        :return: ``(agent_contacts, obstacle_contacts)``, two lists of n ints: how many other agents, and how many
            obstacles or walls, each agent touched during the step (each pair counted once)
        """
        config = self.config
        return self.move(clamp_speed(self.velocities + forces * (config.dt / config.agent_mass), config.v_max))

    def move(self, commanded: np.ndarray) -> tuple[list[int], list[int]]:
        """The Pymunk part of :meth:`step`: set the agents' velocities and let Pymunk move them over the sub-steps.

        :param commanded: ``(n, 2)`` velocities (m/s) after the forces of the step, already clamped to v_max
        :return: as :meth:`step`
        """
        config = self.config
        self._body_velocities[self._agent_rows] = commanded
        pymunk.batch.set_space_bodies(self.space, _VELOCITY_FIELD, self._write_buffer)
        self._agent_pairs.clear()
        self._obstacle_pairs.clear()
        space, substep = self.space._space, self._substep
        for _ in range(config.physics_substeps):
            chipmunk.cpSpaceStep(space, substep)  # Space.step without its Python bookkeeping (see place())
        self._read_buffer.clear()
        pymunk.batch.get_space_bodies(self.space, _STATE_FIELDS, self._read_buffer)
        state = np.frombuffer(self._read_buffer.float_buf(), dtype=np.float64).reshape(-1, 4)[self._agent_rows]
        self.positions, self.velocities = split_state(state, config.v_max)
        agent_contacts = [0] * config.n_agents
        for first, second in self._agent_pairs:
            agent_contacts[first] += 1
            agent_contacts[second] += 1
        obstacle_contacts = [0] * config.n_agents
        for agent, _ in self._obstacle_pairs:
            obstacle_contacts[agent] += 1
        return agent_contacts, obstacle_contacts
