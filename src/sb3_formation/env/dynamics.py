"""How actions move agents: the thesis's holonomic point (eq. 19) or a unicycle, chosen once from ``config.dynamics``.

Two kinds of object, one of each per dynamics:

- a :class:`DynamicsModel` (:func:`dynamics_model`) is what the task's dynamics mean, usable without an engine (by the
  controllers, the safety filter and the ROS nodes as well as by the engine): the command an action gives over a step
  (eq. 19: a point's velocity, or a unicycle's forward speed and turn rate) and its inverse; the point an agent steers
  (its centre, or the point ahead of a unicycle's axle at :attr:`~DynamicsModel.look_ahead`) and the actions that
  follow a velocity of that point; what an agent observes and the global state holds beyond a point's; a command's
  ``Twist``; the Pymunk constraints of its agents;
- a :class:`Dynamics` is the engine's stateful part: it turns a step's actions into what each team's
  :class:`~sb3_formation.env.world.World` is told, lets the worlds move their agents, and reads their positions and
  velocities back (steps 1 to 3 of a step in ``docs/design.md``); it keeps the state its agents have beyond a point's
  (a unicycle's heading and forward speed) and writes what of it an agent observes.

:data:`DYNAMICS_MODELS` is the one place where a dynamics is named: nothing else in the package tells them apart.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar, NamedTuple, cast

import numba
import numpy as np
import pymunk

from sb3_formation.env.config import FormationConfig

if TYPE_CHECKING:
    from sb3_formation.env.stacked import StepTeams
    from sb3_formation.env.state import TeamState
    from sb3_formation.env.world import World

#: what a world's step returns: ``None`` when no agent touched anything, else the agent and obstacle contact counts and
#: the moving obstacles that ran into each agent (:meth:`World.advance`)
Touched = tuple[np.ndarray, np.ndarray, np.ndarray] | None
#: a field an agent observes beyond Table 3.1: name, symbol, size, low, high, unit
#: (:class:`~sb3_formation.env.observations.ObservationField`)
ObservedField = tuple[str, str, int, float, float, str]
#: a field of the global state beyond a point's: name, size, low, high, unit (:func:`~sb3_formation.env.state.state_fields`)
StateField = tuple[str, int, np.ndarray, np.ndarray, str]
#: a ``Twist``'s entries: linear x, linear y (m/s, body frame) and angular z (rad/s)
TwistValues = tuple[float, float, float]
#: Half-length (m) of a unicycle's groove: far more than an agent moves in a sub-step (:mod:`~sb3_formation.env.world`).
GROOVE_HALF_LENGTH = 1.0


@numba.njit(cache=True)
def clamp_speed(velocities: np.ndarray, v_max: float) -> np.ndarray:  # pragma: no cover - compiled
    """Scale down every velocity faster than ``v_max`` (m/s) to ``v_max``, keeping its direction (eq. 19's clamp).

    :param velocities: ``(n, 2)`` velocities (m/s)
    :param v_max: speed limit (m/s)
    :return: a new ``(n, 2)`` array
    """
    clamped: np.ndarray = velocities.copy()
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


def clip_speed(command: np.ndarray, v_max: float) -> np.ndarray:
    """Commanded velocities ``(k, 2)`` (m/s) scaled down, direction kept, to at most ``v_max``."""
    speed = np.linalg.norm(command, axis=-1, keepdims=True)
    clipped: np.ndarray = command * np.minimum(1.0, v_max / np.maximum(speed, 1e-300))
    return clipped


def turned(vector: np.ndarray, yaw: float) -> np.ndarray:
    """A ``(2,)`` vector turned anti-clockwise by ``yaw`` (rad): a body-frame vector into the world frame (``-yaw``:
    back); exact at yaw 0."""
    cos, sin = np.cos(np.array([yaw])), np.sin(np.array([yaw]))
    vectors = np.asarray(vector, dtype=np.float64)[None, :]
    rows = np.stack([cos * vectors[:, 0] - sin * vectors[:, 1], sin * vectors[:, 0] + cos * vectors[:, 1]], axis=1)
    result: np.ndarray = rows[0]
    return result


class PointProblem(NamedTuple):
    """The safety filter's model of the point ``k`` agents steer (:mod:`~sb3_formation.safety.filter`), velocities in
    units of v_max."""

    targets: np.ndarray  #: ``(k, 2)`` the point's velocity u that the proposed actions command
    projections: np.ndarray  #: ``(k, 2, 2)`` the map from the point's velocity to the centre's
    bounds: np.ndarray  #: ``(k, 4, 3)`` the action bounds as rows ``(a_x, a_y, b)``: ``a . u <= b``
    frames: np.ndarray  #: ``(k, 2, 2)`` each agent's frame of actions (identity; a unicycle's rows h, h_perp)


class LateActions(NamedTuple):
    """What the motors of the stepped agents (their rows in order) apply over a step when actions arrive during it (an
    action delay, :class:`~sb3_formation.env.disturbed.Disturber`): each agent's changes of action within the step."""

    times: np.ndarray  #: ``(k, c)`` when each change happens (shares of the step, the first at 0; unused ones 1)
    actions: np.ndarray  #: ``(k, c, 2)`` the action from each change on, motor gain and noise included (may leave [-1, 1])
    counts: np.ndarray  #: ``(k,)`` int64: each agent's number of changes


class DynamicsModel(ABC):
    """What a task's dynamics mean (see the module docstring): stateless, one per task.

    Commands and actions are ``(2,)`` for one agent or ``(k, 2)`` for k agents.

    :param config: the task configuration
    """

    #: the unit of an action's entries (the observed previous action's)
    action_unit: ClassVar[str]
    #: the action bounds alone keep the steered point within v_max (else the safety filter adds a speed polygon)
    bounds_speed: ClassVar[bool]

    def __init__(self, config: FormationConfig) -> None:
        self.config = config

    @property
    def look_ahead(self) -> float:
        """(m) how far ahead of its centre, along its heading, lies the point an agent steers: 0, its centre."""
        return 0.0

    def velocity_changes(self, actions: np.ndarray) -> np.ndarray:
        """Eq. 19: the velocity change (m/s) of each action's force a * F_max over a step, F / m * dt."""
        config = self.config
        changes: np.ndarray = (np.asarray(actions, dtype=np.float64) * config.force_max) * (config.dt / config.agent_mass)
        return changes

    @abstractmethod
    def command(self, actions: np.ndarray, velocities: np.ndarray, forward_speeds: np.ndarray | float) -> np.ndarray:
        """The command an action gives for the next step (eq. 19): what the engine tells the world, the agent node
        its robot.

        :param actions: actions in [-1, 1]
        :param velocities: the agents' world-frame velocities now (m/s)
        :param forward_speeds: a unicycle's forward speeds now (m/s), one per agent
        """

    @abstractmethod
    def action(self, commands: np.ndarray, velocities: np.ndarray, forward_speeds: np.ndarray | float) -> np.ndarray:
        """The action in [-1, 1] that gives ``commands`` (the inverse of :meth:`command`, clipped): how the simulator
        node applies a robot's command. Arguments as :meth:`command`'s."""

    @abstractmethod
    def follow(self, commands: np.ndarray, observations: np.ndarray, layout: dict[str, slice]) -> np.ndarray:
        """The actions that move agents' steered points at commanded world-frame velocities (the controllers'
        actuation).

        :param commands: ``(k, 2)`` commanded velocities (m/s)
        :param observations: ``(k, obs_dim)`` the agents' raw observations (their velocity, and what else they need)
        :param layout: the observation's field name -> slice
        """

    def observed_fields(self) -> list[ObservedField]:
        """The fields an agent observes beyond Table 3.1 (after ``previous_reward``): none."""
        return []

    def observed_values(self, headings: np.ndarray | None) -> np.ndarray:
        """``(k, e)`` the values of :meth:`observed_fields` of agents of ``headings`` ``(k,)`` (``None``: no headings)."""
        return np.zeros((0 if headings is None else len(headings), 0))

    def state_fields(self, n_agents: int) -> list[StateField]:
        """The fields of the global state beyond a point's (after the velocities): none."""
        return []

    def state_values(self, state: TeamState) -> list[np.ndarray]:
        """The values of :meth:`state_fields` of a team's state."""
        return []

    @abstractmethod
    def twist(self, command: np.ndarray, yaw: float) -> TwistValues:
        """The ``Twist`` of a command ``(2,)`` in the robot's body frame, at heading ``yaw`` (rad)."""

    @abstractmethod
    def twist_command(self, twist: TwistValues, yaw: float) -> np.ndarray:
        """The command ``(2,)`` a ``Twist`` gives (the inverse of :meth:`twist`)."""

    @abstractmethod
    def body_velocities(self, velocities: np.ndarray, forward_speeds: np.ndarray) -> np.ndarray:
        """``(k, 2)`` the agents' velocities (m/s) in their body frames (an odometry's twist).

        :param velocities: ``(k, 2)`` world-frame velocities (m/s)
        :param forward_speeds: ``(k,)`` a unicycle's forward speeds (m/s)
        """

    def turn_rates(self, actions: np.ndarray) -> np.ndarray:
        """``(k,)`` the turn rates (rad/s) that ``(k, 2)`` actions give: none."""
        return np.zeros(len(actions))

    def constrain(self, space: pymunk.Space, bodies: list[pymunk.Body]) -> list[pymunk.Body]:
        """Add to ``space`` what holds its agents' ``bodies`` to the dynamics; return the bodies that carry it (none)."""
        return []

    @abstractmethod
    def point_problem(
        self, observations: np.ndarray, layout: dict[str, slice], proposed: np.ndarray, push: float
    ) -> PointProblem:
        """The safety filter's model of the steered point (:class:`PointProblem`) for raw ``observations`` and the
        ``proposed`` actions, ``push`` the velocity change (m/s) of a unit force action over a step."""

    @abstractmethod
    def point_actions(self, solutions: np.ndarray, velocity: np.ndarray, frames: np.ndarray, push: float) -> np.ndarray:
        """The actions that command the steered points' velocities ``solutions`` (units of v_max), clipped to
        [-1, 1] (rounding); ``frames`` and ``push`` as of :meth:`point_problem`."""

    @abstractmethod
    def engine_dynamics(self, starts: np.ndarray) -> Dynamics:
        """The engine's stateful part of these dynamics, for agents stacked by ``starts`` (the first row of each
        team, then the number of rows)."""


class HolonomicModel(DynamicsModel):
    """The thesis's point (eq. 19): the action is a force in the world frame; v <- v + F / m * dt, clamped to v_max.
    A point steers its centre."""

    action_unit = "fraction of F_max"
    bounds_speed = False

    def command(self, actions: np.ndarray, velocities: np.ndarray, forward_speeds: np.ndarray | float) -> np.ndarray:
        """The velocity ``clamp(v + a F_max dt / m, v_max)`` (m/s, world frame)."""
        moved = np.asarray(velocities, dtype=np.float64) + self.velocity_changes(actions)
        commanded: np.ndarray = clamp_speed(moved.reshape(-1, 2), self.config.v_max).reshape(moved.shape)
        return commanded

    def action(self, commands: np.ndarray, velocities: np.ndarray, forward_speeds: np.ndarray | float) -> np.ndarray:
        config = self.config
        per_action = config.force_max * (config.dt / config.agent_mass)
        action = (np.asarray(commands, dtype=np.float64) - np.asarray(velocities, dtype=np.float64)) / per_action
        clipped: np.ndarray = np.clip(action, -1.0, 1.0)
        return clipped

    def follow(self, commands: np.ndarray, observations: np.ndarray, layout: dict[str, slice]) -> np.ndarray:
        return self.reach(commands, observations[:, layout["velocity"]])

    def reach(self, command: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """The action whose force reaches the commanded velocity in one step: the command's speed clipped to v_max,
        ``F = m (v* - v) / dt`` as a fraction of F_max, scaled down (direction kept) to fit [-1, 1]^2.

        :param command: ``(k, 2)`` commanded velocities (m/s)
        :param velocity: ``(k, 2)`` current velocities (m/s)
        """
        config = self.config
        command = clip_speed(command, config.v_max)
        action = config.agent_mass * (command - velocity) / config.dt / config.force_max
        largest = np.abs(action).max(axis=-1, keepdims=True)
        reached: np.ndarray = action / np.maximum(largest, 1.0)
        return reached

    def twist(self, command: np.ndarray, yaw: float) -> TwistValues:
        """The world velocity turned by -yaw into ``linear.x, linear.y``."""
        x, y = turned(np.asarray(command, dtype=np.float64), -yaw).tolist()
        return x, y, 0.0

    def twist_command(self, twist: TwistValues, yaw: float) -> np.ndarray:
        return turned(np.array([twist[0], twist[1]]), yaw)

    def body_velocities(self, velocities: np.ndarray, forward_speeds: np.ndarray) -> np.ndarray:
        """A point's body frame is the world's."""
        return velocities

    def point_problem(
        self, observations: np.ndarray, layout: dict[str, slice], proposed: np.ndarray, push: float
    ) -> PointProblem:
        v_max, count = self.config.v_max, len(observations)
        velocity = observations[:, layout["velocity"]]
        bounds = np.zeros((count, 4, 3))
        commanded = velocity + push * proposed
        speed = np.linalg.norm(commanded, axis=1, keepdims=True)
        targets = commanded * np.minimum(1.0, v_max / np.maximum(speed, 1e-300)) / v_max  # the env's speed clamp
        frames = np.tile(np.eye(2), (count, 1, 1))
        low, high = (velocity - push) / v_max, (velocity + push) / v_max  # |a| <= 1 on each axis
        for axis in range(2):
            bounds[:, 2 * axis, axis], bounds[:, 2 * axis, 2] = 1.0, high[:, axis]
            bounds[:, 2 * axis + 1, axis], bounds[:, 2 * axis + 1, 2] = -1.0, -low[:, axis]
        return PointProblem(targets, frames, bounds, frames)

    def point_actions(self, solutions: np.ndarray, velocity: np.ndarray, frames: np.ndarray, push: float) -> np.ndarray:
        actions = (solutions * self.config.v_max - velocity) / push
        clipped: np.ndarray = np.clip(actions, -1.0, 1.0)
        return clipped

    def engine_dynamics(self, starts: np.ndarray) -> Dynamics:
        return HolonomicDynamics(self, starts)


class UnicycleModel(DynamicsModel):
    """A unicycle (:meth:`~sb3_formation.env.world.World.drive`): the action's first entry is a forward force along
    the heading, its second a turn rate as a share of ``max_turn_rate``. It observes the cosine and sine of its heading.

    A unicycle steers the point ``l = v_max / w_max`` (:attr:`look_ahead`) ahead of its axle: that point moves at
    ``v h + l w h_perp`` for forward speed v and turn rate w (h the heading, h_perp h turned by +90 deg), so any
    velocity of it is reachable (feedback linearisation, :meth:`steer`), and a sideways one of v_max turns the unicycle
    at its limit w_max.
    """

    action_unit = "forward: of F_max; turn: of max_turn_rate"
    bounds_speed = True

    @property
    def look_ahead(self) -> float:
        """(m) ``l = v_max / max_turn_rate``."""
        return self.config.v_max / self.config.max_turn_rate

    def command(self, actions: np.ndarray, velocities: np.ndarray, forward_speeds: np.ndarray | float) -> np.ndarray:
        """The forward speed ``clip(v_f + a_0 F_max dt / m, +-v_max)`` (m/s) and turn rate ``a_1 max_turn_rate``
        (rad/s)."""
        config = self.config
        forward = np.clip(forward_speeds + self.velocity_changes(actions)[..., 0], -config.v_max, config.v_max)
        turns = np.asarray(actions, dtype=np.float64)[..., 1] * config.max_turn_rate
        return np.stack([forward, turns], axis=-1)

    def action(self, commands: np.ndarray, velocities: np.ndarray, forward_speeds: np.ndarray | float) -> np.ndarray:
        config = self.config
        per_action = config.force_max * (config.dt / config.agent_mass)
        commands = np.asarray(commands, dtype=np.float64)
        action = np.stack([(commands[..., 0] - forward_speeds) / per_action, commands[..., 1] / config.max_turn_rate], axis=-1)
        clipped: np.ndarray = np.clip(action, -1.0, 1.0)
        return clipped

    def follow(self, commands: np.ndarray, observations: np.ndarray, layout: dict[str, slice]) -> np.ndarray:
        return self.steer(commands, observations[:, layout["velocity"]], observations[:, layout["heading"]])

    def point_velocities(self, forward: np.ndarray, turn_rates: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """``(k, 2)`` the velocity ``v h + l w h_perp`` (m/s) of the steered point.

        :param forward: ``(k,)`` forward speeds v (m/s)
        :param turn_rates: ``(k,)`` turn rates w (rad/s)
        :param heading: ``(k, 2)`` the headings' (cos, sin)
        """
        normal = np.stack([-heading[:, 1], heading[:, 0]], axis=1)
        velocities: np.ndarray = forward[:, None] * heading + (self.look_ahead * turn_rates)[:, None] * normal
        return velocities

    def drive_of(self, velocities: np.ndarray, heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of :meth:`point_velocities`: the forward speeds ``v = u . h`` (m/s) and the turn rates as shares
        of their limit, ``w / w_max = (u . h_perp) / (l w_max)``, that move the steered point at ``(k, 2)``
        velocities u (m/s)."""
        forward = (velocities * heading).sum(axis=-1)
        sideways = velocities[:, 1] * heading[:, 0] - velocities[:, 0] * heading[:, 1]
        return forward, sideways / self.point_turn_speed

    @property
    def point_turn_speed(self) -> float:
        """(m/s) ``l w_max``: the steered point's sideways speed at the turn-rate limit (v_max)."""
        return self.look_ahead * self.config.max_turn_rate

    def steer(self, command: np.ndarray, velocity: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """A unicycle's action (forward force, turn rate) that moves its steered point at the commanded velocity
        (feedback linearisation, :meth:`drive_of`). The forward force reaches v in one step, ``F = m (v - v_f) / dt``
        with v_f = velocity . h, as a share of F_max clipped to [-1, 1]; the turn action is w / w_max, within [-1, 1]
        since the command's speed is at most v_max.

        :param command: ``(k, 2)`` commanded velocities (m/s), their speed clipped to v_max first
        :param velocity: ``(k, 2)`` current velocities (m/s), along the headings
        :param heading: ``(k, 2)`` the headings' (cos, sin)
        """
        config = self.config
        forward, turn = self.drive_of(clip_speed(command, config.v_max), heading)
        current = (velocity * heading).sum(axis=-1)
        push = np.clip(config.agent_mass * (forward - current) / config.dt / config.force_max, -1.0, 1.0)
        return np.stack([push, turn], axis=-1)

    def observed_fields(self) -> list[ObservedField]:
        """An extension of Table 3.1: the unicycle's heading, in the world frame."""
        return [("heading", "(cos theta^i, sin theta^i)", 2, -1.0, 1.0, "unit")]

    def observed_values(self, headings: np.ndarray | None) -> np.ndarray:
        if headings is None:
            raise ValueError("a unicycle observes its heading, and none was given")
        headings = np.asarray(headings, dtype=np.float64)
        return np.stack([np.cos(headings), np.sin(headings)], axis=-1)

    def state_fields(self, n_agents: int) -> list[StateField]:
        """The agents' headings."""
        return [("headings", n_agents, np.full(n_agents, -math.pi), np.full(n_agents, math.pi), "rad, agent 0 first")]

    def state_values(self, state: TeamState) -> list[np.ndarray]:
        if state.headings is None:
            raise ValueError("the global state of unicycles holds their headings, and this state has none (a recording?)")
        return [state.headings]

    def twist(self, command: np.ndarray, yaw: float) -> TwistValues:
        """The forward speed as ``linear.x``, the turn rate as ``angular.z``."""
        return float(command[0]), 0.0, float(command[1])

    def twist_command(self, twist: TwistValues, yaw: float) -> np.ndarray:
        return np.array([twist[0], twist[2]])

    def body_velocities(self, velocities: np.ndarray, forward_speeds: np.ndarray) -> np.ndarray:
        """Along the heading only."""
        return np.stack([forward_speeds, np.zeros(len(forward_speeds))], axis=1)

    def turn_rates(self, actions: np.ndarray) -> np.ndarray:
        turn_rates: np.ndarray = np.clip(actions[:, 1], -1.0, 1.0) * self.config.max_turn_rate
        return turn_rates

    def constrain(self, space: pymunk.Space, bodies: list[pymunk.Body]) -> list[pymunk.Body]:
        """Each agent's groove (no sideways motion, see :mod:`~sb3_formation.env.world`) on a kinematic carrier of its
        own, without shapes, at rest."""
        carriers = []
        for body in bodies:
            carrier = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            carrier.position = body.position
            groove = pymunk.GrooveJoint(carrier, body, (-GROOVE_HALF_LENGTH, 0), (GROOVE_HALF_LENGTH, 0), (0, 0))
            groove.max_bias = 0.0
            space.add(carrier, groove)
            carriers.append(carrier)
        return carriers

    def point_problem(
        self, observations: np.ndarray, layout: dict[str, slice], proposed: np.ndarray, push: float
    ) -> PointProblem:
        """Targets ``v' h + l w h_perp``, projections ``h h^T`` (the centre moves along h with the forward speed
        h . u), bounds of the forward speed and the turn rate."""
        v_max, count = self.config.v_max, len(observations)
        velocity, heading = observations[:, layout["velocity"]], observations[:, layout["heading"]]
        bounds = np.zeros((count, 4, 3))
        normal = np.stack([-heading[:, 1], heading[:, 0]], axis=1)
        frames = np.stack([heading, normal], axis=1)  # rows: h, h_perp
        current = (velocity * heading).sum(axis=1)
        forward = np.clip(current + push * proposed[:, 0], -v_max, v_max)
        turn = proposed[:, 1] * self.config.max_turn_rate
        targets = self.point_velocities(forward, turn, heading) / v_max
        fast = np.minimum(v_max, current + push) / v_max
        slow = np.maximum(-v_max, current - push) / v_max
        sideways = self.point_turn_speed / v_max
        bounds[:, 0, :2], bounds[:, 0, 2] = heading, fast
        bounds[:, 1, :2], bounds[:, 1, 2] = -heading, -slow
        bounds[:, 2, :2], bounds[:, 2, 2] = normal, sideways
        bounds[:, 3, :2], bounds[:, 3, 2] = -normal, sideways
        return PointProblem(targets, heading[:, :, None] * heading[:, None, :], bounds, frames)

    def point_actions(self, solutions: np.ndarray, velocity: np.ndarray, frames: np.ndarray, push: float) -> np.ndarray:
        heading = frames[:, 0]
        forward, turn = self.drive_of(solutions * self.config.v_max, heading)
        current = (velocity * heading).sum(axis=-1)
        actions = np.stack([(forward - current) / push, turn], axis=1)
        clipped: np.ndarray = np.clip(actions, -1.0, 1.0)
        return clipped

    def engine_dynamics(self, starts: np.ndarray) -> Dynamics:
        return UnicycleDynamics(self, starts)


#: ``FormationConfig.dynamics`` -> its model: the one place where a dynamics is named
DYNAMICS_MODELS: dict[str, type[DynamicsModel]] = {"holonomic": HolonomicModel, "unicycle": UnicycleModel}


def dynamics_model(config: FormationConfig) -> DynamicsModel:
    """The model of the task's dynamics (``config.dynamics``, :data:`DYNAMICS_MODELS`)."""
    return DYNAMICS_MODELS[config.dynamics](config)


class Moved(NamedTuple):
    """The stepped teams' agents after the physics of a step."""

    positions: np.ndarray  #: ``(k, 2)`` (m), the stepped teams' agents one team after the other
    velocities: np.ndarray  #: ``(k, 2)`` (m/s)
    touched: list[Touched]  #: each stepped team's contacts (:meth:`World.advance`), in the order of the teams


class Dynamics(ABC):
    """How actions move the agents of an engine's teams (see the module docstring).

    :param model: the task's dynamics (the teams differ in ``n_agents`` only)
    :param starts: the first row of each team, then the number of rows
    """

    def __init__(self, model: DynamicsModel, starts: np.ndarray) -> None:
        self.model, self.config = model, model.config
        self.starts = starts
        #: ``(agents, e)`` what every agent observes of its state beyond a point's (:meth:`observe`)
        self.observed = np.zeros((int(starts[-1]), sum(field[2] for field in model.observed_fields())))

    @abstractmethod
    def move(
        self,
        actions: np.ndarray,
        velocities: np.ndarray,
        worlds: list[World],
        stepped: StepTeams,
        late: LateActions | None = None,
    ) -> Moved:
        """Move the stepped teams' agents over a step.

        :param actions: ``(agents, 2)`` actions (within [-1, 1] unless a motor gain or noise acts), a row for every agent
        :param velocities: ``(agents, 2)`` velocities (m/s) before the step
        :param worlds: every team's world
        :param stepped: the teams to move
        :param late: actions that arrive during the step (instead of ``actions``)
        """

    def _move_late(self, late: LateActions, state: np.ndarray, worlds: list[World]) -> list[Touched]:
        """Move the agents of ``worlds`` (their rows one world after the other) over a step of late actions: in each of
        the step's equal sub-steps, every agent moves at the mean of its motion within it
        (:func:`~sb3_formation.env.disturbed.substep_plan`), so that without contacts it ends the sub-step where its
        changes of action take it, and the step ends at the motion of its last change (:meth:`World.advance_plan`).

        :param state: ``(k, 2)`` a point's velocity, or a unicycle's forward speed and turn rate, before the step
        :return: each world's contacts
        """
        from sb3_formation.env.disturbed import substep_plan  # the env's disturbances build on the dynamics

        config = self.config
        push = config.force_max * config.dt / config.agent_mass
        limits = (float(config.v_max), float(config.max_turn_rate), self.model.bounds_speed)
        plan = substep_plan(cast(int, config.physics_substeps), state, late, push, limits)
        rows = np.cumsum([0, *(world.n_agents for world in worlds)])
        return [
            world.advance_plan(plan[:, rows[k] : rows[k + 1]], state[rows[k] : rows[k + 1]]) for k, world in enumerate(worlds)
        ]

    @abstractmethod
    def reset(self, rows: slice, world: World) -> None:
        """Start the episode of a team (its agents' ``rows``) placed in ``world``."""

    def observe(self, rows: slice | np.ndarray) -> np.ndarray:
        """What every agent observes of its state beyond a point's, :attr:`observed`, with agents ``rows`` brought up
        to date (:meth:`DynamicsModel.observed_values`)."""
        return self.observed

    @abstractmethod
    def headings_of(self, rows: slice) -> np.ndarray | None:
        """The headings (rad) of agents ``rows``, or ``None`` for agents without one."""

    @abstractmethod
    def forward_speeds_of(self, rows: slice) -> np.ndarray | None:
        """The forward speeds (m/s) of agents ``rows``, or ``None`` for agents without a heading."""


class HolonomicDynamics(Dynamics):
    """Points (:class:`HolonomicModel`): the world moves them at the commanded velocities."""

    def move(
        self,
        actions: np.ndarray,
        velocities: np.ndarray,
        worlds: list[World],
        stepped: StepTeams,
        late: LateActions | None = None,
    ) -> Moved:
        v_max, starts = self.config.v_max, self.starts
        if late is None:
            commanded = self.model.command(actions, velocities, 0.0)
            touched = [worlds[team].advance(commanded[starts[team] : starts[team + 1]]) for team in stepped.teams]
        else:
            own = velocities if stepped.rows is None else velocities[stepped.rows]
            touched = self._move_late(late, own.copy(), [worlds[team] for team in stepped.teams])
        positions, moved = split_state(np.concatenate([worlds[team].agent_states for team in stepped.teams]), v_max)
        return Moved(positions, moved, touched)

    def reset(self, rows: slice, world: World) -> None:
        """A point keeps no state beyond its position and velocity."""

    def headings_of(self, rows: slice) -> np.ndarray | None:
        return None

    def forward_speeds_of(self, rows: slice) -> np.ndarray | None:
        return None


class UnicycleDynamics(Dynamics):
    """Unicycles (:class:`UnicycleModel`): keeps every agent's heading and forward speed."""

    def __init__(self, model: DynamicsModel, starts: np.ndarray) -> None:
        super().__init__(model, starts)
        #: every agent's heading (rad, anti-clockwise from +x) and forward speed (m/s)
        self.headings, self.forward_speeds = np.zeros(int(starts[-1])), np.zeros(int(starts[-1]))

    def move(
        self,
        actions: np.ndarray,
        velocities: np.ndarray,
        worlds: list[World],
        stepped: StepTeams,
        late: LateActions | None = None,
    ) -> Moved:
        teams, starts = stepped.teams, self.starts
        if late is None:
            commands = self.model.command(actions, velocities, self.forward_speeds)
            forward, turns = commands[:, 0], commands[:, 1]
            touched = [
                worlds[team].drive(forward[starts[team] : starts[team + 1]], turns[starts[team] : starts[team + 1]])
                for team in teams
            ]
        else:
            speeds = self.forward_speeds if stepped.rows is None else self.forward_speeds[stepped.rows]
            state = np.stack([speeds, np.zeros(len(speeds))], axis=1)
            touched = self._move_late(late, state, [worlds[team] for team in teams])
        positions = np.concatenate([worlds[team].agent_states[:, :2] for team in teams])
        headings = np.concatenate([worlds[team].headings for team in teams])
        speeds = np.concatenate([worlds[team].forward_speeds for team in teams])
        self.headings = stepped.merged(self.headings, headings)
        self.forward_speeds = stepped.merged(self.forward_speeds, speeds)
        return Moved(positions, speeds[:, None] * np.stack([np.cos(headings), np.sin(headings)], axis=1), touched)

    def reset(self, rows: slice, world: World) -> None:
        self.headings, self.forward_speeds = self.headings.copy(), self.forward_speeds.copy()
        self.headings[rows], self.forward_speeds[rows] = world.headings, 0.0

    def observe(self, rows: slice | np.ndarray) -> np.ndarray:
        self.observed[rows] = self.model.observed_values(self.headings[rows])
        return self.observed

    def headings_of(self, rows: slice) -> np.ndarray | None:
        return self.headings[rows]

    def forward_speeds_of(self, rows: slice) -> np.ndarray | None:
        return self.forward_speeds[rows]
