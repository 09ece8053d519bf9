"""The Pymunk world: the only stateful physics object. Forces in, positions and velocities out.

Agents are dynamic circles that do not rotate; obstacles are static circles and walls (Pymunk segments with a
radius: capsules); the world's border is four thick static segments. Each environment step applies the agents'
forces as the second-order integrator of eq. 19 (semi-implicit Euler, as Pymunk itself integrates): v <- v + F / m *
dt, then the speed is clamped to v_max, then Pymunk moves the bodies over ``config.physics_substeps`` sub-steps and
resolves contacts (inelastic, frictionless).

Unicycle agents (:class:`~sb3_formation.env.dynamics.UnicycleModel`, :meth:`World.drive`) also have a heading theta,
kept here (Pymunk's bodies still do not rotate). The engine turns the forward force into a forward speed v in [-v_max,
v_max] and the turn action into a turn rate w. In every sub-step of length h an agent moves along the arc of (v, w):
its velocity is the chord ``v sinc(w h / 2)`` in the direction ``theta + w h / 2``, so that without contacts its path
is exactly a circle of radius v / w, and theta advances by w h. Pymunk moves positions with the velocity its last
solve left before it solves the next one, so each sub-step sets the next arc's velocity as a force and lets Pymunk
solve it with the contacts (a command therefore acts from the next sub-step on). The no-sideways constraint is part of
that solve: each unicycle's centre runs in a groove (a ``GrooveJoint`` without positional correction, which its model
adds: :meth:`~sb3_formation.env.dynamics.DynamicsModel.constrain`) along the next chord, carried by a body of its own
that is put on the agent at the start of every sub-step, so contacts can slow or stop an agent along its heading but
cannot push it sideways (as wheels that do not skid). The solved velocity along the chord is the next forward speed;
what is left across it is the solver's residual, dropped, and the largest such speed of a step is
:attr:`World.sideways_speed` (:data:`SIDEWAYS_TOLERANCE` bounds it). Only Pymunk's overlap correction, which pushes
overlapping bodies apart along the contact normal, can still move a jammed agent sideways (less than 2 mm per step in
the test of a jam).
Contacts are counted once per pair per environment step: after each
sub-step the space's touching pairs are read in one call of Pymunk's batch API (every obstacle and wall hangs on its
own static body, so a pair of bodies names the obstacle), not through a Python collision callback per contact and
sub-step, which made a step 1.7x as long when agents press on walls (``benchmarks/env_throughput.py``).
"""

from __future__ import annotations

import math
from typing import Any, cast

import numba
import numpy as np
import pymunk
import pymunk.batch
from pymunk._chipmunk import lib as chipmunk

from sb3_formation.env.config import COLLISION_BIAS, FormationConfig
from sb3_formation.env.dynamics import clamp_speed, dynamics_model, split_state
from sb3_formation.env.movers import MovingObstacles
from sb3_formation.env.scenarios import Scenario

BORDER_THICKNESS = 1.0  #: m; the border's inner faces lie exactly on [0, W] x [0, H]
COLLISION_SLOP = 1e-3  #: m; Pymunk's allowed overlap (its default 0.1 is for pixel units)
_STATE_FIELDS = pymunk.batch.BodyFields.POSITION | pymunk.batch.BodyFields.VELOCITY
_VELOCITY_FIELD = pymunk.batch.BodyFields.VELOCITY
#: what is read of each of the space's arbiters (pairs of shapes whose bounding boxes met lately): its two bodies' ids
#: and its number of contact points in the last sub-step (0 for a pair no longer touching)
_ARBITER_FIELDS = pymunk.batch.ArbiterFields.BODY_A_ID | pymunk.batch.ArbiterFields.BODY_B_ID
_ARBITER_FIELDS |= pymunk.batch.ArbiterFields.CONTACT_COUNT
# The C iterators behind pymunk.batch's functions, called directly with queries made once per world: the Python
# wrappers build a query on every call, which cost more than the physics of a step
_GET_BODIES = pymunk.batch.ffi.addressof(pymunk.batch.lib, "pmSpaceBodyGetIteratorFuncBatched")
_SET_BODIES = pymunk.batch.ffi.addressof(pymunk.batch.lib, "pmSpaceBodySetIteratorFuncBatched")
_GET_ARBITERS = pymunk.batch.ffi.addressof(pymunk.batch.lib, "pmSpaceArbiterIteratorFuncBatched")
_SPARE_VALUES = 8  #: values past the end of a world's state array (see World.place)
#: The most sideways speed (m/s per m/s of v_max) a unicycle keeps after a sub-step's solve: the solver's residual
#: (asserted with agents pressing on walls and on each other, tests/test_unicycle.py).
SIDEWAYS_TOLERANCE = 1e-3


@numba.njit(cache=True)
def count_contacts(
    arbiters: np.ndarray, body_ids: np.ndarray, body_roles: np.ndarray, n_agents: int, n_obstacles: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """How many other agents, and how many obstacles or walls, each agent touched, each pair counted once.

    :param arbiters: ``(k, 3)`` rows (body a id, body b id, contact points) read after each sub-step of a step
    :param body_ids: the space's body ids, sorted
    :param body_roles: for each of ``body_ids``: the agent's index, or ``-1 - i`` for obstacle or wall i
    :return: two ``(n_agents,)`` int arrays, and the ``(n_agents, n_obstacles)`` bool pairs that touched
    """
    agent_pairs = np.zeros((n_agents, n_agents), dtype=np.bool_)
    obstacle_pairs = np.zeros((n_agents, n_obstacles), dtype=np.bool_)
    for row in range(arbiters.shape[0]):
        if arbiters[row, 2] == 0:
            continue
        first = body_roles[np.searchsorted(body_ids, arbiters[row, 0])]
        second = body_roles[np.searchsorted(body_ids, arbiters[row, 1])]
        if first >= 0 and second >= 0:
            agent_pairs[min(first, second), max(first, second)] = True
        elif first >= 0:
            obstacle_pairs[first, -1 - second] = True
        elif second >= 0:
            obstacle_pairs[second, -1 - first] = True
    agents = np.zeros(n_agents, dtype=np.int64)
    for first in range(n_agents):
        for second in range(first + 1, n_agents):
            if agent_pairs[first, second]:
                agents[first] += 1
                agents[second] += 1
    obstacles = np.zeros(n_agents, dtype=np.int64)
    for agent in range(n_agents):
        obstacles[agent] = obstacle_pairs[agent].sum()
    return agents, obstacles, obstacle_pairs


def wrap_angles(angles: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into (-pi, pi] (-pi itself where rounding puts a tiny negative angle a full turn away)."""
    wrapped: np.ndarray = math.pi - np.mod(math.pi - angles, 2 * math.pi)
    return wrapped


class World:
    """One team's Pymunk space, built from a :class:`Scenario`; :meth:`place` puts the next episode's in the same space.
    The world holds the scenario's agents: a crossing's holds every formation's
    (:func:`~sb3_formation.env.scenarios.crossing_scenario`), which then touch each other as agents.

    :param config: task configuration (world size, agent radius and mass, v_max, dt, sub-steps)
    :param scenario: placement of agents, goal and obstacles (validated by the caller)
    """

    def __init__(self, config: FormationConfig, scenario: Scenario) -> None:
        self.config = config
        self.space = pymunk.Space()
        self.space.collision_slop = COLLISION_SLOP
        self.space.collision_bias = COLLISION_BIAS  # the substeps of the config are chosen for it
        self.space.iterations = 20  # keeps a column of 16 agents pressed on a wall within 1 cm
        # Pymunk's batch API reads and writes every body of the space at once, in the space's own order, from and to
        # numpy arrays of this world (their memory is the buffers'); it reads the arbiters once per sub-step,
        # appending to one buffer over a step
        self._read_buffer, self._read = self._buffer_and_query(_STATE_FIELDS)
        self._place_buffer, self._place = self._buffer_and_query(_STATE_FIELDS)  # movers' positions and velocities
        self._write_buffer, self._write = self._buffer_and_query(_VELOCITY_FIELD)
        self._arbiter_buffer, self._arbiter_query = self._buffer_and_query(_ARBITER_FIELDS)
        self._substep = config.dt / cast(int, config.physics_substeps)  # an int once the config is built
        self.place(scenario)

    def place(self, scenario: Scenario) -> None:
        """Empty the space and put the walls, the obstacles and the agents of ``scenario`` in it, as a new world would.

        Reusing one space for every episode keeps memory flat: a Pymunk space is freed only by Python's cyclic
        garbage collector, which lets thousands of old ones wait.

        :param scenario: placement of agents, goal and obstacles (validated by the caller)
        """
        config = self.config
        self.space.remove(*self.space.constraints, *self.space.shapes, *self.space.bodies)
        # each wall and obstacle hangs on a static body of its own, of this episode (the space's own static body would
        # keep every old shape); a contact's pair of bodies then names the obstacle
        self._obstacle_bodies: list[pymunk.Body] = []
        self._add_border()
        for x, y, radius in scenario.obstacles:
            self._add_obstacle(pymunk.Circle(None, float(radius), (float(x), float(y))))
        for x0, y0, x1, y1, thickness in scenario.walls:  # capsules, as the scene's walls are
            self._add_obstacle(pymunk.Segment(None, (float(x0), float(y0)), (float(x1), float(y1)), float(thickness) / 2))
        #: the scenario's moving obstacles, stepped by :meth:`move_obstacles` (kinematic bodies after the static ones)
        self.movers = MovingObstacles(
            scenario.movers,
            config.dt,
            config.world_width,
            config.world_height,
            np.asarray(scenario.obstacles),
            np.asarray(scenario.walls),
            config.agent_radius,
        )
        self._mover_bodies: list[pymunk.Body] = []
        #: how many agents the world holds (a crossing's: every formation's)
        self.n_agents = n_agents = len(scenario.agent_positions)
        self._intended = np.zeros((n_agents, 2))  # the agents' commanded velocities (m/s) in the last step
        # where the agents and the movers were at the start of the last step of the movers (m)
        self._step_start = (np.asarray(scenario.agent_positions), self.movers.positions)
        for mover in scenario.movers:
            body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            body.position = tuple(mover.start.tolist())
            self.space.add(body, pymunk.Circle(body, mover.radius))
            self._obstacle_bodies.append(body)
            self._mover_bodies.append(body)
        self.agent_bodies: list[pymunk.Body] = []
        #: agents whose motors stopped (:meth:`halt`): they command no motion and are obstacles to the others
        self.halted = np.zeros(n_agents, dtype=bool)
        #: unicycles' headings (rad, anti-clockwise from +x, in (-pi, pi]) and forward speeds (m/s)
        given = len(scenario.headings)
        self.headings = wrap_angles(np.array(scenario.headings)) if given else np.full(n_agents, scenario.facing)
        self.forward_speeds = np.zeros(n_agents)
        self._half_turns = np.zeros(n_agents)  # w h / 2 of the arc the agents' velocities follow
        #: the largest sideways speed (m/s) a unicycle had after a sub-step's contact solve, over the last step
        self.sideways_speed = 0.0
        for x, y in scenario.agent_positions:
            body = pymunk.Body(config.agent_mass, float("inf"))
            body.position = (float(x), float(y))
            self.space.add(body, pymunk.Circle(body, config.agent_radius))
            self.agent_bodies.append(body)
        #: unicycles' groove carriers (kinematic bodies without shapes, at rest; see the module docstring)
        self._carriers: list[pymunk.Body] = dynamics_model(config).constrain(self.space, self.agent_bodies)
        ids = [body.id for body in self.agent_bodies] + [body.id for body in self._obstacle_bodies]
        roles = list(range(len(self.agent_bodies))) + [-1 - index for index in range(len(self._obstacle_bodies))]
        order = np.argsort(ids)
        self._body_ids = np.array(ids, dtype=np.uintp)[order]
        self._body_roles = np.array(roles, dtype=np.int64)[order]
        self._agent_roles = np.searchsorted(self._body_ids, np.array(ids[: len(self.agent_bodies)], dtype=np.uintp))
        id_buffer = pymunk.batch.Buffer()
        pymunk.batch.get_space_bodies(self.space, pymunk.batch.BodyFields.BODY_ID, id_buffer)
        body_ids = list(np.frombuffer(id_buffer.int_buf(), dtype=np.uintp))  # in the space's order
        rows = [body_ids.index(body.id) for body in self.agent_bodies]
        contiguous = rows == list(range(rows[0], rows[0] + len(rows)))
        self._agent_rows = slice(rows[0], rows[0] + len(rows)) if contiguous else np.array(rows)
        self._mover_rows = np.array([body_ids.index(body.id) for body in self._mover_bodies], dtype=np.int64)
        self._body_velocities = np.zeros((len(body_ids), 2))  # static bodies keep velocity 0, movers their step's
        self._write_buffer.set_float_buf(self._body_velocities.ravel())  # Pymunk reads this array's memory
        # Pymunk writes x, y, v_x, v_y of every body into this array's memory; it would reallocate it (as if it were
        # its own) when fewer than 3 values are left free after a body's velocity, hence the spare room
        states = np.zeros(4 * len(body_ids) + _SPARE_VALUES)
        self._read_buffer.set_float_buf(states)
        self._body_states = states[: 4 * len(body_ids)].reshape(-1, 4)
        self._placed_states = np.zeros((len(body_ids), 4))  # what move_obstacles writes into every body
        self._place_buffer.set_float_buf(self._placed_states.ravel())
        # Space.step's Python bookkeeping (new bodies' checks, removed shapes) runs here, once per episode: a step of 0 s
        # does only that (Chipmunk returns at once), and advance() then calls Chipmunk's step directly
        self.space.step(0.0)
        self._read_states()

    @staticmethod
    def _buffer_and_query(fields: pymunk.batch.BodyFields | pymunk.batch.ArbiterFields) -> tuple[pymunk.batch.Buffer, Any]:
        """A Pymunk batch buffer and the C query (``pmBatchedData``) that reads or writes ``fields`` through it."""
        buffer = pymunk.batch.Buffer()
        query = pymunk.batch.ffi.new("pmBatchedData *")
        query.fields = fields.value
        query.floatArray, query.intArray = buffer._float_arr, buffer._int_arr
        return buffer, query

    def _add_border(self) -> None:
        width, height, half = self.config.world_width, self.config.world_height, BORDER_THICKNESS / 2
        corners = [(-half, -half), (width + half, -half), (width + half, height + half), (-half, height + half)]
        for start, end in zip(corners, corners[1:] + corners[:1]):
            self._add_obstacle(pymunk.Segment(None, start, end, half))

    def _add_obstacle(self, shape: pymunk.Shape) -> None:
        """Add a wall or obstacle's ``shape`` (made without a body) on a static body of its own."""
        shape.body = body = pymunk.Body(body_type=pymunk.Body.STATIC)
        self.space.add(body, shape)
        self._obstacle_bodies.append(body)

    def move_obstacles(self) -> None:
        """Start a step of the moving obstacles (:class:`~sb3_formation.env.movers.MovingObstacles`): put each where it
        is now, with the velocity that takes it where it is at the end of the step; the agents' sub-steps then move it.
        Reacting walkers see the agents as they are now."""
        if not self._mover_bodies:
            return
        placed, rows = self._placed_states, self._mover_rows
        placed[:] = self._body_states  # every other body is given back the state it has
        placed[rows, :2] = self.movers.positions
        agents = self.agent_states
        self._step_start = (agents[:, :2].copy(), self.movers.positions)  # the step's start, for _rammed
        placed[rows, 2:] = self._body_velocities[rows] = self.movers.step(agents[:, :2], agents[:, 2:])
        self._place_buffer._float_arr.num = 0  # the position Pymunk reads from
        chipmunk.cpSpaceEachBody(self.space._space, _SET_BODIES, self._place)

    def halt(self, agent: int) -> None:
        """Stop an agent's motors for the rest of the episode: from the next step on it commands no motion (it stands
        where it stopped, moving only while something pushes it), and a contact with it is an obstacle contact of
        the agent that touched it; its own contacts are no longer counted.

        :param agent: the agent's index
        """
        self.halted[agent] = True
        self._body_roles[self._agent_roles[agent]] = -1 - len(self._obstacle_bodies) - agent

    def _halted_commands(self, commands: np.ndarray) -> np.ndarray:
        """``commands`` ``(..., n, 2)`` with the halted agents' rows zero (a copy; ``commands`` when none is halted)."""
        if not self.halted.any():
            return commands
        stopped: np.ndarray = np.array(commands, dtype=np.float64)
        stopped[..., self.halted, :] = 0.0
        return stopped

    def step(self, forces: np.ndarray) -> tuple[list[int], list[int]]:
        """Advance one environment step of ``config.dt`` seconds under ``forces``.

        :param forces: ``(n, 2)`` forces (N), held over the step
        :return: ``(agent_contacts, obstacle_contacts)``, two lists of n ints: how many other agents, and how many
            obstacles or walls, each agent touched during the step (each pair counted once)
        """
        config = self.config
        if self._carriers:
            raise ValueError(f"World.step moves free points; {config.dynamics} agents move with World.drive")
        contacts = self.advance(clamp_speed(self.velocities + forces * (config.dt / config.agent_mass), config.v_max))
        if contacts is None:
            return [0] * self.n_agents, [0] * self.n_agents
        return contacts[0].tolist(), contacts[1].tolist()  # the movers that ran into an agent: see advance

    def advance(self, commanded: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The Pymunk part of :meth:`step`: set the agents' velocities and let Pymunk move them over the sub-steps.

        :param commanded: ``(n, 2)`` velocities (m/s) after the forces of the step, already clamped to v_max
        :return: ``None`` when no agent touched anything, else three ``(n,)`` int arrays: the contact counts of
            :meth:`step`, and how many of each agent's obstacle contacts were moving obstacles that ran into it
            (:meth:`_rammed`)
        """
        self._body_velocities[self._agent_rows] = self._intended = self._halted_commands(commanded)
        self._write_velocities()
        self._arbiter_buffer._int_arr.num = 0
        for _ in range(cast(int, self.config.physics_substeps)):  # an int once the config is built
            self._substep_once(self._substep)
        self._read_states()
        return self._contacts()

    def drive(self, forward: np.ndarray, turn_rates: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """A unicycle step (see the module docstring): drive the agents at forward speeds ``forward`` while they turn
        at ``turn_rates``; updates :attr:`headings`, :attr:`forward_speeds` and :attr:`sideways_speed`.

        :param forward: ``(n,)`` forward speeds (m/s) after the forces of the step, within [-v_max, v_max]
        :param turn_rates: ``(n,)`` turn rates (rad/s), held over the step
        :return: as :meth:`advance`
        """
        self._arbiter_buffer._int_arr.num = 0
        self.sideways_speed = 0.0
        if self.halted.any():
            forward, turn_rates = np.where(self.halted, 0.0, forward), np.where(self.halted, 0.0, turn_rates)
        if self._mover_bodies:  # what _rammed reads
            self._intended = self._along_headings(forward)
        substeps = cast(int, self.config.physics_substeps)  # an int once the config is built
        self._drive_part(np.asarray(forward, dtype=np.float64), turn_rates, substeps, self._substep)
        return self._contacts()

    def advance_plan(self, plan: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """A step whose actions arrive during it (:meth:`~sb3_formation.env.dynamics.Dynamics.move` with late actions):
        each sub-step at its row of ``plan`` ``(substeps, n, 2)``, then the step ends at ``last`` ``(n, 2)``; motions
        are points' velocities (m/s), or unicycles' forward speeds (m/s) and turn rates (rad/s). What the solver
        changes in a sub-step is carried on to the next and to the end (a sub-step of another length would rescale the
        solver's remembered impulses, which a very short one makes explode, so the plan keeps them equal).

        :return: as :meth:`advance`
        """
        self._arbiter_buffer._int_arr.num = 0
        self.sideways_speed = 0.0
        plan, last = self._halted_commands(plan), self._halted_commands(last)
        if self._mover_bodies:  # what _rammed reads
            self._intended = self._along_headings(last[:, 0]) if self._carriers else last
        if self._carriers:
            carried = np.zeros(len(last))
            for speeds, turn_rates in zip(plan[:, :, 0], plan[:, :, 1]):
                self._drive_part(speeds + carried, turn_rates, 1, self._substep)
                carried = self.forward_speeds - speeds
            self.forward_speeds = np.clip(last[:, 0] + carried, -self.config.v_max, self.config.v_max)
            return self._contacts()
        moved = np.zeros_like(last)
        for velocities in plan:
            self._body_velocities[self._agent_rows] = velocities + moved
            self._write_velocities()
            self._substep_once(self._substep)
            self._read_states()
            moved = self.agent_states[:, 2:] - velocities
        self._body_velocities[self._agent_rows] = last + moved
        self._write_velocities()
        self._read_states()
        return self._contacts()

    def _drive_part(self, speeds: np.ndarray, turn_rates: np.ndarray, substeps: int, substep: float) -> None:
        """Drive the agents at forward ``speeds`` and ``turn_rates`` over ``substeps`` sub-steps of ``substep`` seconds
        (the body of :meth:`drive`); leaves the forward speeds in :attr:`forward_speeds` and raises
        :attr:`sideways_speed` to the part's largest."""
        config = self.config
        half_turns = 0.5 * turn_rates * substep
        chords = np.sinc(half_turns / math.pi)  # sin(w h / 2) / (w h / 2): the chord's share of the arc
        sideways = self.sideways_speed
        for _ in range(substeps):
            # Pymunk first moves the agents with the velocity its last solve left, along the arc that began at the
            # heading; then it solves the velocity of the next arc, which the force sets and the groove holds
            turned = self.headings + 2 * self._half_turns
            middle = turned + half_turns
            directions = np.stack([np.cos(middle), np.sin(middle)], axis=1)
            targets = (speeds * chords)[:, None] * directions
            forces = config.agent_mass * (targets - self.agent_states[:, 2:]) / substep
            moving = zip(
                self.agent_bodies, self._carriers, self.agent_states[:, :2].tolist(), middle.tolist(), forces.tolist()
            )
            for body, carrier, position, angle, force in moving:
                carrier.position, carrier.angle, body.force = position, angle, force
            self._substep_once(substep)
            self._read_states()
            self.headings, self._half_turns = wrap_angles(turned), half_turns
            velocities = self.agent_states[:, 2:]
            along = velocities[:, 0] * directions[:, 0] + velocities[:, 1] * directions[:, 1]
            across = velocities[:, 1] * directions[:, 0] - velocities[:, 0] * directions[:, 1]
            sideways = max(sideways, float(np.abs(across).max()))
            speeds = np.clip(along / chords, -config.v_max, config.v_max)
        self.forward_speeds, self.sideways_speed = speeds, sideways

    def _write_velocities(self) -> None:
        """Give every body the velocity of its row of ``_body_velocities`` (static bodies: 0)."""
        self._write_buffer._float_arr.num = 0  # the position Pymunk reads from
        chipmunk.cpSpaceEachBody(self.space._space, _SET_BODIES, self._write)

    def _substep_once(self, substep: float) -> None:
        """One Pymunk sub-step of ``substep`` seconds, and the touching pairs after it appended to the arbiter buffer."""
        chipmunk.cpSpaceStep(self.space._space, substep)  # Space.step without its Python bookkeeping (see place())
        chipmunk.cpSpaceEachCachedArbiter(self.space._space, _GET_ARBITERS, self._arbiter_query)

    def _along_headings(self, speeds: np.ndarray) -> np.ndarray:
        """``(n, 2)`` velocities (m/s) of forward ``speeds`` along the agents' headings now."""
        velocities: np.ndarray = np.asarray(speeds)[:, None] * np.stack([np.cos(self.headings), np.sin(self.headings)], 1)
        return velocities

    def _contacts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The contact counts of the sub-steps since the arbiter buffer was emptied (see :meth:`advance`): agents,
        obstacles or walls, and of those the moving obstacles that ran into the agent (:meth:`_rammed`)."""
        if self._arbiter_buffer._int_arr.num == 0:  # no pair of shapes near each other
            return None
        records = np.frombuffer(self._arbiter_buffer.int_buf(), dtype=np.uintp).reshape(-1, 3)
        n_agents, n_obstacles = self.n_agents, len(self._obstacle_bodies)
        halted = n_agents if self.halted.any() else 0  # halted agents' roles follow the obstacles' (halt)
        agents, obstacles, pairs = count_contacts(records, self._body_ids, self._body_roles, n_agents, n_obstacles + halted)
        return agents, obstacles, self._rammed(pairs[:, n_obstacles - len(self._mover_bodies) : n_obstacles])

    def _rammed(self, touched: np.ndarray) -> np.ndarray:
        """How many moving obstacles ran into each agent in the step: of the movers it touched (``touched``, ``(n, k)``
        bool), those towards whose centre (at the start of the step) the velocity it commanded for the step had no
        positive component: it was braking, standing or moving away. A touch of any other kind is one the agent drove
        into."""
        rammed = np.zeros(len(touched), dtype=np.int64)
        for agent, mover in zip(*np.nonzero(touched)):
            towards = self._step_start[1][mover] - self._step_start[0][agent]
            rammed[agent] += float(np.dot(self._intended[agent], towards)) <= 0.0
        return rammed

    def _read_states(self) -> None:
        """Read every body's position and velocity from Pymunk into :attr:`agent_states`' array."""
        self._read_buffer._float_arr.num = 0  # the position Pymunk writes to
        chipmunk.cpSpaceEachBody(self.space._space, _GET_BODIES, self._read)

    @property
    def positions(self) -> np.ndarray:
        """``(n, 2)`` agent centres (m), a new array."""
        return split_state(self.agent_states, self.config.v_max)[0]

    @property
    def velocities(self) -> np.ndarray:
        """``(n, 2)`` agent velocities (m/s), clamped to v_max as every step does, a new array."""
        return split_state(self.agent_states, self.config.v_max)[1]

    @property
    def agent_states(self) -> np.ndarray:
        """``(n, 4)`` rows x, y, v_x, v_y (m, m/s) of the agents as Pymunk left them (speeds not clamped); a view."""
        return self._body_states[self._agent_rows]
